"""`hdp bench link --episodes`: the same episodes with the graph split across two hosts and on one.

Split: two network namespaces joined by a link of --episode-link Mbit/s; on the workstation
`hdp launch --nodes planner_node,controller_node`, both taking compressed frames; on the robot
host a driver process (this module's main) starts `hdp launch --nodes sim_bridge_node`, watches
the graph as `hdp demo` does (demo.watcher) and runs the episodes: per task, seeds SEED ..
SEED+N-1, each reset through /hdp/sim/reset and ended by the planner's outcome. The driver sits
on the robot host because the watcher takes the raw front camera (to know a scene is up): there
it stays off the link, which carries what the graph needs alone. One host: the same driver with
`hdp launch` (all three nodes, raw frames, the localhost profile) in the machine's own
namespace. The -p parameters go to both graphs.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from . import netns

HDP_LAUNCH = [sys.executable, '-m', 'hdp_tools.cli.main', 'launch']
COMPRESSED = ['-p', 'planner_node:image_transport:=compressed', '-p', 'controller_node:image_transport:=compressed']
KEPT = ('task', 'seed', 'outcome', 'reason', 'success', 'wall_s')      # of demo.watcher's episode record


def compare_episodes(args, domain: int, logs: Path, say) -> dict:
    """Run --episodes per task split across two hosts, then on one host; episode_comparison()."""
    tasks = [t.strip() for t in args.tasks.split(',') if t.strip()]
    user = [flag for param in args.param for flag in ('-p', param)]
    driver = [sys.executable, '-m', 'hdp_bringup.link_episodes', '--tasks', ','.join(tasks), '--seed', str(args.seed),
              '--episodes', str(args.episodes), '--timeout', str(args.episode_timeout), '--logs', str(logs)]
    say(f'episodes split across the hosts ({args.episode_link:g} Mbit/s, compressed) ...')
    with netns.two_hosts(rate_mbit=args.episode_link) as (robot, workstation), \
            open(logs / 'split_workstation.log', 'w') as workstation_log:
        workstation.popen([*HDP_LAUNCH, '--nodes', 'planner_node,controller_node', *COMPRESSED, *user],
                          env=netns.discovery_env(args.discovery, domain, robot),
                          stdout=workstation_log, stderr=subprocess.STDOUT)
        split = _drive(robot.popen, [*driver, '--name', 'split_robot', '--',
                                     *HDP_LAUNCH, '--nodes', 'sim_bridge_node', *user],
                       netns.discovery_env(args.discovery, domain, workstation))
    say('the same episodes on one host ...')
    one_host = _drive(subprocess.Popen, [*driver, '--name', 'one_host', '--', *HDP_LAUNCH, *user],
                      dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1'))
    return episode_comparison(tasks, args.episodes, args.episode_link, one_host, split)


def _drive(popen, argv: list, env: dict) -> dict:
    """The driver's JSON (its progress goes to our stderr as it comes)."""
    process = popen(argv, env=env, stdout=subprocess.PIPE, text=True)
    out, _ = process.communicate()
    lines = out.strip().splitlines()
    if not lines:
        return {'episodes': [], 'problem': f'the episode driver exited with code {process.returncode}'}
    return json.loads(lines[-1])


def episode_comparison(tasks: list[str], episodes: int, link_mbit: float, one_host: dict, split: dict) -> dict:
    """Successes per task on one host and split, and the (task, seed)s that ended differently."""
    runs = {'one_host': {(e['task'], e['seed']): e for e in one_host['episodes']},
            'split': {(e['task'], e['seed']): e for e in split['episodes']}}
    counts = {task: {'episodes': episodes, **{name: sum(e['success'] for (t, _), e in run.items() if t == task)
                                              for name, run in runs.items()}}
              for task in tasks}

    def ended(name, key):
        return runs[name][key]['outcome'] if key in runs[name] else 'not run'
    differ = [f'{task} {seed} (one host {ended("one_host", (task, seed))}, split {ended("split", (task, seed))})'
              for task, seed in sorted(set(runs['one_host']) | set(runs['split']))
              if ended('one_host', (task, seed)) != ended('split', (task, seed))]
    return {'link_mbit': link_mbit, 'tasks': counts, 'differ': differ,
            'problems': {'one host': one_host['problem'], 'split': split['problem']},
            'one_host': one_host['episodes'], 'split': split['episodes']}


# -- the driver process ---------------------------------------------------------------------------
def drive(args) -> dict:
    """Start args.launch, wait for the whole graph, run the episodes: {'episodes', 'problem'}."""
    from hdp_msgs_py.msg import String

    from .demo.watcher import DemoNode, GraphDown, Interrupted, run_episode, wait_for_graph, watched_graph

    def say(text: str) -> None:
        print(f'[link] {args.name}: {text}', file=sys.stderr, flush=True)
    records, problem = [], None
    domain = int(os.environ.get('ROS_DOMAIN_ID', '0'))
    try:
        with watched_graph({args.name: args.launch}, args.logs, domain,
                           lambda: DemoNode(on_segment=lambda segment: None), say) as session:
            wait_for_graph(session, say, time.monotonic())
            for task in args.tasks.split(','):
                for seed in range(args.seed, args.seed + args.episodes):
                    session.node.episode = None
                    session.node.reset.publish(String(data=json.dumps({'task': task, 'seed': seed})))
                    record, _ = run_episode(session, seed, None, args.timeout, dict, say)
                    say(f"{task} seed {seed}: {record['outcome']} after {record['wall_s']:.1f} s")
                    records.append({key: record[key] for key in KEPT})
    except (GraphDown, Interrupted) as why:
        problem = str(why)
        say(f'stopped: {why}')
    return {'episodes': records, 'problem': problem}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description='episode driver of hdp bench link (internal; see the module doc)')
    parser.add_argument('--tasks', required=True)
    parser.add_argument('--seed', type=int, required=True)
    parser.add_argument('--episodes', type=int, required=True)
    parser.add_argument('--timeout', type=float, required=True)
    parser.add_argument('--logs', type=Path, required=True)
    parser.add_argument('--name', required=True, help="this host's launch, for its log's name")
    parser.add_argument('launch', nargs=argparse.REMAINDER, help='-- then the hdp launch command line')
    args = parser.parse_args(argv)
    args.launch = args.launch[1:] if args.launch[:1] == ['--'] else args.launch
    result = drive(args)
    print(json.dumps(result), flush=True)
    return 0 if result['problem'] is None else 1


if __name__ == '__main__':
    sys.exit(main())
