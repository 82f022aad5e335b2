"""The `hdp demo` command: arguments, the ROS domain, the node processes, the outputs.

Starts sim_bridge_node, planner_node and controller_node as `hdp launch` does
(launch_cli.running_nodes), waits until they are connected, runs the episodes through
watcher.run_episode and writes what it saw.
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import sys
import time
from pathlib import Path

from hdp_controller.methods import METHODS      # controller_node's `method` parameter
from hdp_msgs_py.msg import String

from ..launch_cli import NODES, default_params_file, node_commands
from .cpu import cpu_seconds, read_stats
from .episode_log import segment_line
from .figures import figures, format_figures
from .media import write_episode_files
from .recording import BagRecorder
from .watcher import DemoNode, GraphDown, Interrupted, Session, run_episode, wait_for_graph, watched_graph

SAMPLERS = ('ddim', 'ddpm')                            # controller_node's `sampler` parameter
DEFAULT_SEED = 1000            # evaluation seeds start here, apart from every training seed
SAFE_DOMAINS = range(1, 102)   # ROS_DOMAIN_IDs whose ports stay below Linux's ephemeral range
RECORD_DRAIN_S = 0.5           # spun after the last episode, so the recording gets the last messages


def pick_domain(env, rng: random.Random) -> tuple[int, bool]:
    """(ROS_DOMAIN_ID, picked): the environment's, else one drawn from SAFE_DOMAINS so that the
    demo's graph does not meet another graph on this machine (discovery is localhost-only)."""
    text = (env.get('ROS_DOMAIN_ID') or '').strip()
    if not text:
        return rng.choice(SAFE_DOMAINS), True
    if not text.isdigit() or int(text) > 232:
        raise ValueError(f'ROS_DOMAIN_ID must be an integer 0..232, got {text!r}')
    return int(text), False


def configure(parser) -> None:
    """Run the HDP graph on one task and show it: segments, a GIF, a trajectory plot, figures.

    Starts sim_bridge_node, planner_node and controller_node (as `hdp launch`), waits until they
    are connected, sends the episode's instruction and prints one line per segment. Writes to
    OUT: <task>_seed<S>.gif (front camera), <task>_seed<S>_trajectory.png (joints over time,
    end-effector path and NBPs), summary.json (segments, stage times, CPU per node) and the
    nodes' output in logs/. A refused instruction (the planner's vocabulary, or a first NBP below
    min_confidence) is that episode's failure, as the harness counts it, and the next episode
    runs. Exit 0 when every episode succeeded, 1 on a failure or timeout, 2 on bad arguments or
    when every episode was refused, 130 on Ctrl-C; the nodes are stopped on every exit.
    """
    parser.add_argument('--task', required=True, metavar='TASK',
                        help='e.g. reach_target or open_drawer (an unknown name lists the eleven tasks)')
    parser.add_argument('--instruction', default=None,
                        help="what to say (default: the episode's own instruction for the task and seed)")
    parser.add_argument('--phrasing', choices=('seen', 'heldout', 'paraphrase'), default=None,
                        help='say what `hdp eval hierarchy --phrasings P` says on each seed (a training phrasing, '
                             'the held-out one or a paraphrase), to compare the graph with the harness')
    parser.add_argument('--seed', type=int, default=DEFAULT_SEED,
                        help=f'scene seed (default {DEFAULT_SEED}: evaluation seeds, never trained on)')
    parser.add_argument('--episodes', type=int, default=1,
                        help='episodes on seeds SEED, SEED+1, ...; the sim is reset between them and the '
                             'graph stays up, so the figures get p50/p95 (default 1)')
    parser.add_argument('--out', type=Path, default=Path('demo_out'), help='output directory (default demo_out/)')
    parser.add_argument('--method', choices=METHODS, default='rkd', help='low-level method (default rkd)')
    parser.add_argument('--sampler', choices=SAMPLERS, default='ddim',
                        help='RK-Diffuser sampler: ddim (5 steps, unguided), ddpm (100, guided) (default ddim)')
    parser.add_argument('--timeout', type=float, default=180.0, metavar='S',
                        help='seconds per episode, instruction to the end (default 180)')
    parser.add_argument('--params-file', type=Path, default=None,
                        help=f'node parameters (default: {default_params_file()})')
    parser.add_argument('--agent-checkpoint', type=Path, default=None,
                        help="planner_node's agent (default: the parameter file's, models/hdp_nbp_agent_11tasks.pt); "
                             'the same flag as hdp eval hierarchy, so both run the same models')
    parser.add_argument('--low-level-checkpoint', type=Path, default=None,
                        help="controller_node's RK-Diffuser (default: the parameter file's, models/rk_diffuser_11tasks.pt)")
    parser.add_argument('--sensor-profile', choices=('ideal', 'd415'), default=None,
                        help="sim_bridge_node's camera sensor model: ideal renders or a D415's depth noise, holes "
                             "and colour jitter (default: the parameter file's, ideal)")
    parser.add_argument('--json', action='store_true',
                        help='print summary.json on stdout (progress goes to stderr)')
    parser.add_argument('--record', action='store_true',
                        help='also record the run as an MCAP bag in OUT/bag (robot, TF, cameras, NBPs, '
                             'trajectories) for Foxglove or ros2 bag play')
    parser.epilog = ('ROS_DOMAIN_ID: the environment\'s if set, else a free-looking one is picked at random '
                     f'from {SAFE_DOMAINS.start}..{SAFE_DOMAINS.stop - 1} and printed.')
    parser.set_defaults(func=run)


def argument_problem(args, tasks) -> str | None:
    """Why these arguments cannot run, or None."""
    if args.task not in tasks:
        return f'unknown task {args.task!r}; tasks: {", ".join(tasks)}'
    if args.instruction is not None and not args.instruction.strip():
        return '--instruction is empty'
    if args.instruction is not None and getattr(args, 'phrasing', None):
        return '--instruction and --phrasing exclude each other'
    if args.seed < 0 or args.episodes < 1 or not args.timeout > 0:
        return '--seed must be >= 0, --episodes >= 1 and --timeout > 0'
    params = args.params_file or default_params_file()
    if not params.is_file():
        return f'no parameter file {params}'
    for flag in ('agent_checkpoint', 'low_level_checkpoint'):
        path = getattr(args, flag, None)
        if path is not None and not path.is_file():
            return f'--{flag.replace("_", "-")}: no file {path}'
    if getattr(args, 'record', False) and (args.out / 'bag').exists():
        return f'{args.out / "bag"} exists: a recording is never overwritten; move it or choose another --out'
    return None


def parameter_overrides(args) -> list[str]:
    """'node:parameter:=value' for what the arguments set over the parameter file."""
    overrides = [f'sim_bridge_node:task:={args.task}', f'sim_bridge_node:seed:={args.seed}',
                 f'controller_node:method:={args.method}', f'controller_node:sampler:={args.sampler}']
    if args.agent_checkpoint:
        overrides.append(f'planner_node:checkpoint:={args.agent_checkpoint.resolve()}')
    if args.low_level_checkpoint:
        overrides.append(f'controller_node:checkpoint:={args.low_level_checkpoint.resolve()}')
    if getattr(args, 'sensor_profile', None):
        overrides.append(f'sim_bridge_node:sensor_profile:={args.sensor_profile}')
    return overrides


def json_stdout():
    """The real stdout, for the summary alone: fd 1 goes to stderr from now on, so what C libraries
    print there (pybullet's banners, flushed at exit) cannot mix into the JSON."""
    sys.stdout.flush()
    real = os.fdopen(os.dup(1), 'w')
    os.dup2(2, 1)
    return real


def run(args) -> int:
    from hdp_sim_bridge.tasks import TASKS
    json_out = json_stdout() if args.json else None
    say_to = sys.stderr if args.json else sys.stdout

    def say(text: str) -> None:
        print(f'[demo] {text}', file=say_to, flush=True)

    problem = argument_problem(args, TASKS)
    try:
        domain, picked = pick_domain(os.environ, random.Random())
    except ValueError as err:
        problem = problem or str(err)
    if problem:
        print(f'hdp demo: {problem}', file=sys.stderr)
        return 2
    commands = node_commands(list(NODES), args.params_file or default_params_file(), parameter_overrides(args))
    logs = args.out / 'logs'
    logs.mkdir(parents=True, exist_ok=True)
    say(f'ROS_DOMAIN_ID={domain} ' + ('(picked at random; set ROS_DOMAIN_ID to choose)' if picked
                                       else '(from the environment)'))
    say(f'node output: {logs}/<node>.log')
    for name in NODES:
        (logs / f'{name}.log').unlink(missing_ok=True)      # this run's output only
    records, logs_by_episode, code = [], [], 1
    started = time.monotonic()
    try:
        with watched_graph(commands, logs, domain, lambda: DemoNode(lambda s: say(segment_line(s))), say) as session:
            code = _run(session, args, records, logs_by_episode, started, say)
    except Interrupted as why:
        say(f'{why}: stopped the nodes')
        code = 130
    except GraphDown as why:
        say(f'{why}; stopped the nodes (see {logs}/)')
        code = 1
    if records:
        _write_outputs(args, domain, picked, records, logs_by_episode, started, say, json_out)
    return code


def _run(session: Session, args, records, logs_by_episode, started, say) -> int:
    """Wait for the graph, run the episodes; the exit code (exit_code, 1 on a timeout)."""
    node = session.node
    recorder = BagRecorder(node, args.out / 'bag') if args.record else None     # before latched topics come
    try:
        return _episodes(session, args, records, logs_by_episode, started, say)
    finally:
        if recorder is not None:
            with contextlib.suppress(Interrupted, GraphDown):     # what is still on its way: the outcome
                session.spin_until(lambda: False, RECORD_DRAIN_S)
            recorder.close(episode_metadata(records))
            say(f"recorded {sum(recorder.counts.values())} messages in {recorder.path} (Foxglove opens it)")


def episode_metadata(records: list) -> dict:
    """A one-episode recording's hdp.* metadata, as `ros2 bag record --custom-data` would carry it,
    so that it trains like a recorded demonstration; none for several episodes (not one episode)."""
    if len(records) != 1:
        return {'hdp.episodes': len(records)}
    record = records[0]
    return {'hdp.task': record['task'], 'hdp.seed': record['seed'], 'hdp.variation': record['variation'],
            'hdp.instruction': record['instruction'], 'hdp.success': str(bool(record['success'])).lower()}


def _episodes(session: Session, args, records, logs_by_episode, started, say) -> int:
    node = session.node
    wait_for_graph(session, say, started)
    ticks = os.sysconf('SC_CLK_TCK')
    pids = {name: proc.pid for name, proc in session.procs.items()}

    def cpu_sample():
        return cpu_seconds(pids, read_stats(), ticks)
    for i in range(args.episodes):
        seed = args.seed + i
        if i:
            node.episode = None
            node.reset.publish(String(data=json.dumps({'task': args.task, 'seed': seed})))
        record, log = run_episode(session, seed, args.instruction, args.timeout, cpu_sample, say, args.phrasing)
        records.append(record)
        logs_by_episode.append(log)
        if record['outcome'] == 'timeout':        # the planner may still be at it: a reset would mislead it
            say(f"seed {seed}: TIMEOUT ({record['reason']}); no further episodes")
            for line in record['stall']:
                say(f'  {line}')
            return 1
        if record['outcome'] == 'refused':     # one failed episode, as the harness counts it
            say(f"seed {seed}: REFUSED by planner_node ({record['reason']})")
            continue
        verdict = 'succeeded' if record['success'] else f"FAILED ({record['outcome']}: {record['reason']})"
        when = f" in {record['success_s']:.1f} s" if record['success'] else ''
        say(f"seed {seed}: {verdict}{when}, {len(record['segments'])} segments")
    return exit_code(records)


def exit_code(records: list) -> int:
    """0: every episode succeeded; 2: the planner refused every one; 1: otherwise."""
    if all(r['outcome'] == 'refused' for r in records):
        return 2
    return 0 if all(r['success'] for r in records) else 1


def _write_outputs(args, domain, picked, records, logs_by_episode, started, say, json_out) -> None:
    """Each episode's GIF and plot (none for a refused instruction: nothing moved), summary.json,
    and the figures table when there were segments to measure."""
    figs = figures(records)
    for record, log in zip(records, logs_by_episode):
        if record['outcome'] != 'refused':
            title = (f"{record['task']} seed {record['seed']}: {record['instruction']!r} ({args.method}, "
                     f"{args.sampler}) -> {'success' if record['success'] else record['outcome']}")
            write_episode_files(log, record, args.out, title)
    summary = {'task': args.task, 'method': args.method, 'sampler': args.sampler, 'ros_domain_id': domain,
               'ros_domain_id_picked': picked, 'total_wall_s': round(time.monotonic() - started, 1),
               'figures': figs, 'episodes': records}
    (args.out / 'summary.json').write_text(json.dumps(summary, indent=1))
    if figs['observe_predict_s']['n']:
        say('figures:\n' + format_figures(figs))
    files = [f for r in records for f in (r.get('gif'), r.get('plot')) if f]
    say(f"wrote {', '.join(str(args.out / f) for f in [*files, 'summary.json'])}")
    if json_out is not None:
        print(json.dumps(summary, indent=1), file=json_out, flush=True)
