"""`hdp launch`: the HDP graph as processes, what `ros2 launch hdp_bringup hdp_graph.launch.py` does.

sim_bridge_node, planner_node and controller_node each run in a process of their own with
their section of config/hdp_graph.yaml; planner_node and controller_node are managed nodes,
and a lifecycle_manager process (lifecycle_manager.py) brings those started to active,
controller first. Output lines are prefixed with the node's name;
SIGINT/SIGTERM go on to every node. What happens when a node exits is ros2 launch's choice,
per node: by default the others keep running (the command ends when every node has exited);
`--exit-on-node-exit` stops the graph (ros2 launch's on_exit=Shutdown()); `--respawn NODES`
restarts those nodes after `--respawn-delay` seconds (respawn=True, respawn_delay). The exit
code is non-zero when a node exited with an error.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from hdp_controller.methods import METHODS   # controller_node's low levels (imports no torch)

# node name -> package; the executable is the node's name (hdp_graph.launch.py reads this too).
NODES = {'sim_bridge_node': 'hdp_sim_bridge', 'planner_node': 'hdp_planner', 'controller_node': 'hdp_controller'}
# The managed nodes in the order they go up: the controller is active before the planner sends it work.
MANAGED = ('controller_node', 'planner_node')
MANAGER = 'lifecycle_manager'
STOP_GRACE_S = 15.0            # for a node to exit after SIGINT, before SIGTERM and then SIGKILL
ON_EXIT = ('keep', 'shutdown', 'respawn')    # what a node's exit does to the graph


def default_params_file() -> Path:
    """config/hdp_graph.yaml of this source tree (editable install), else the installed share/ copy."""
    source = Path(__file__).resolve().parents[1] / 'config' / 'hdp_graph.yaml'
    return source if source.is_file() else Path(sys.prefix) / 'share' / 'hdp_bringup' / 'config' / 'hdp_graph.yaml'


def configure(parser) -> None:
    """Start the HDP graph (sim bridge, planner, controller) as processes; Ctrl-C stops it."""
    parser.add_argument('--params-file', type=Path, default=None,
                        help=f'node parameters (default: {default_params_file()})')
    parser.add_argument('--task', help="the simulated task (default: the params file's)")
    parser.add_argument('--seed', help="the scene seed (default: the params file's)")
    parser.add_argument('--method', help=f"controller_node's low level: {' | '.join(METHODS)}")
    parser.add_argument('--nodes', default=','.join(NODES),
                        help='comma-separated nodes to start (default: all three; '
                             'planner_node,controller_node for a real robot); with either of those, '
                             f'{MANAGER} too')
    parser.add_argument('-p', '--param', action='append', default=[], metavar='NODE:NAME:=VALUE',
                        help='override one parameter, e.g. controller_node:method:=planner (repeatable)')
    parser.add_argument('--exit-on-node-exit', action='store_true',
                        help='stop every node when one exits (default: the others keep running)')
    parser.add_argument('--respawn', default='', metavar='NODES',
                        help='comma-separated nodes to start again whenever they exit')
    parser.add_argument('--respawn-delay', type=float, default=1.0, metavar='S',
                        help='seconds before a respawn (default 1.0)')
    parser.set_defaults(func=run)


def launch_overrides(task=None, seed=None, method=None) -> dict[str, dict]:
    """node -> the parameters the launch arguments set (hdp_graph.launch.py's task, seed, method);
    ValueError for an unknown task or method or a seed that is not a whole number >= 0."""
    from hdp_data.instructions import TASKS
    overrides: dict[str, dict] = {}
    if task is not None:
        if task not in TASKS:
            raise ValueError(f'unknown task {task!r}; tasks: {", ".join(TASKS)}')
        overrides.setdefault('sim_bridge_node', {})['task'] = task
    if seed is not None:
        if not str(seed).isdigit():
            raise ValueError(f'seed must be a whole number >= 0, got {seed!r}')
        overrides.setdefault('sim_bridge_node', {})['seed'] = int(seed)
    if method is not None:
        if method not in METHODS:
            raise ValueError(f'unknown method {method!r}; methods: {", ".join(METHODS)}')
        overrides['controller_node'] = {'method': method}
    return overrides


def exit_policies(nodes, exit_on_node_exit: bool, respawn) -> dict[str, str]:
    """node -> one of ON_EXIT; ValueError for a respawned node that is not started."""
    stray = [n for n in respawn if n not in nodes]
    if stray:
        raise ValueError(f'--respawn names node(s) not started: {stray}; started: {", ".join(nodes)}')
    return {n: 'respawn' if n in respawn else 'shutdown' if exit_on_node_exit else 'keep' for n in nodes}


def managed(nodes) -> list[str]:
    """The managed nodes among ``nodes``, in the order the lifecycle manager brings them up."""
    return [n for n in MANAGED if n in nodes]


def node_commands(nodes: list[str], params_file: Path, overrides: list[str]) -> dict[str, list[str]]:
    """node -> the command line that starts it with this Python, its parameters and overrides;
    with a managed node among them, the lifecycle manager's last (it manages those started)."""
    unknown = [n for n in nodes if n not in NODES]
    if unknown or not nodes:
        raise ValueError(f'unknown node(s) {unknown}; nodes: {", ".join(NODES)}')
    modules = {n: f'{NODES[n]}.{n}' for n in nodes}
    if managed(nodes):
        modules[MANAGER] = f'hdp_bringup.{MANAGER}'
    commands = {n: [sys.executable, '-m', module, '--ros-args', '--params-file', str(params_file)]
                for n, module in modules.items()}
    if MANAGER in commands:
        commands[MANAGER] += ['-p', f'node_names:=[{",".join(managed(nodes))}]']
    for override in overrides:
        node, _, assignment = override.partition(':')
        if node not in (*NODES, MANAGER) or ':=' not in assignment:
            raise ValueError(f'--param takes NODE:NAME:=VALUE with NODE one of {", ".join((*NODES, MANAGER))}, '
                             f'got {override!r}')
        if node in commands:
            commands[node] += ['-p', assignment]
    return commands


def _relay(name: str, stream, lock: threading.Lock) -> None:
    for line in stream:
        with lock:
            sys.stdout.write(f'[{name}] {line}' if line.endswith('\n') else f'[{name}] {line}\n')
            sys.stdout.flush()


def stop_nodes(procs: dict, say) -> None:
    """SIGINT every running node, then SIGTERM and SIGKILL to those that outstay the grace period."""
    for sig, grace in ((signal.SIGINT, STOP_GRACE_S), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
        running = [p for p in procs.values() if p.poll() is None]
        if not running:
            return
        if sig != signal.SIGINT:
            say(f'{len(running)} node(s) still running: {sig.name}')
        for proc in running:
            proc.send_signal(sig)
        for proc in running:
            try:
                proc.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                pass


@contextlib.contextmanager
def running_nodes(commands: dict[str, list[str]], output, say, env: dict | None = None):
    """Start each node (name -> command line) and yield name -> Popen; stop them all on leaving.

    ``output(name)`` is where the node's stdout and stderr go (subprocess.PIPE or an open file).
    Each node gets a session of its own: a terminal's Ctrl-C reaches only the caller, which
    passes it on once, on leaving (stop_nodes), however it leaves.
    """
    procs = {}
    try:
        for name, command in commands.items():
            procs[name] = start_node(name, command, output, say, env)
        yield procs
    finally:
        stop_nodes(procs, say)


def start_node(name: str, command: list[str], output, say, env: dict | None = None) -> subprocess.Popen:
    """One node process in a session of its own (see running_nodes)."""
    env = dict(os.environ if env is None else env, PYTHONUNBUFFERED='1')
    proc = subprocess.Popen(command, stdout=output(name), stderr=subprocess.STDOUT, text=True, env=env,
                            start_new_session=True)
    say(f'started {name} (pid {proc.pid})')
    return proc


def run(args) -> int:
    params_file = args.params_file or default_params_file()
    if not params_file.is_file():
        print(f'hdp launch: no parameter file {params_file}', file=sys.stderr)
        return 2
    try:
        nodes = [n.strip() for n in args.nodes.split(',') if n.strip()]
        arguments = [f'{node}:{name}:={value}' for node, values in
                     launch_overrides(args.task, args.seed, args.method).items() for name, value in values.items()]
        commands = node_commands(nodes, params_file, arguments + args.param)     # -p has the last word
        policies = exit_policies(list(commands), args.exit_on_node_exit,
                             [n.strip() for n in args.respawn.split(',') if n.strip()])
        if args.respawn_delay < 0:
            raise ValueError(f'--respawn-delay must be >= 0, got {args.respawn_delay}')
    except ValueError as err:
        print(f'hdp launch: {err}', file=sys.stderr)
        return 2

    lock = threading.Lock()

    def say(text: str) -> None:
        with lock:
            print(f'[launch] {text}', flush=True)

    stop = threading.Event()
    requested: list[str] = []

    def on_signal(signum, frame):
        requested.append(signal.Signals(signum).name)
        stop.set()

    def relay(name, proc):
        relays.append(threading.Thread(target=_relay, args=(name, proc.stdout, lock), daemon=True))
        relays[-1].start()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    relays, exited, shutdown_by = [], {}, None
    try:
        with running_nodes(commands, lambda name: subprocess.PIPE, say) as procs:
            for name, proc in procs.items():
                relay(name, proc)
            respawn_at: dict[str, float] = {}
            while shutdown_by is None and len(exited) < len(procs) and not stop.wait(0.2):
                for name, proc in procs.items():
                    if name in exited or name in respawn_at or proc.poll() is None:
                        continue
                    code, policy = proc.returncode, policies[name]
                    if policy == 'respawn':
                        say(f'{name} exited with code {code}; respawning it in {args.respawn_delay:.1f} s')
                        respawn_at[name] = time.monotonic() + args.respawn_delay
                    elif policy == 'shutdown':
                        say(f'{name} exited with code {code}; stopping the other nodes')
                        shutdown_by = name
                        break
                    else:
                        exited[name] = code
                        running = len(procs) - len(exited)
                        say(f'{name} exited with code {code}; ' + (f'{running} node(s) keep running' if running
                                                                    else 'every node has exited'))
                for name in [n for n, due in respawn_at.items() if time.monotonic() >= due]:
                    del respawn_at[name]
                    procs[name] = start_node(name, commands[name], lambda _: subprocess.PIPE, say)
                    relay(name, procs[name])
            if requested:
                say(f'{requested[0]}: stopping the nodes')
    finally:
        for thread in relays:
            thread.join(timeout=2.0)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if shutdown_by is not None:
        code = procs[shutdown_by].returncode
        return code if code > 0 else 1
    failed = {n: c for n, c in {**{n: p.returncode for n, p in procs.items()}, **exited}.items() if c != 0}
    if failed:
        say(f'nodes that did not exit cleanly: {failed}')
    return 1 if failed else 0
