"""`hdp launch`: the HDP graph as processes, what `ros2 launch hdp_bringup hdp_graph.launch.py` does.

sim_bridge_node, planner_node and controller_node each run in a process of their own with
their section of config/hdp_graph.yaml. Output lines are prefixed with the node's name;
SIGINT/SIGTERM go on to every node; if one node exits, the others are stopped and the
command exits non-zero.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

# node name -> package; the executable is the node's name (hdp_graph.launch.py reads this too).
NODES = {'sim_bridge_node': 'hdp_sim_bridge', 'planner_node': 'hdp_planner', 'controller_node': 'hdp_controller'}
STOP_GRACE_S = 15.0            # for a node to exit after SIGINT, before SIGTERM and then SIGKILL


def default_params_file() -> Path:
    """config/hdp_graph.yaml of this source tree (editable install), else the installed share/ copy."""
    source = Path(__file__).resolve().parents[1] / 'config' / 'hdp_graph.yaml'
    return source if source.is_file() else Path(sys.prefix) / 'share' / 'hdp_bringup' / 'config' / 'hdp_graph.yaml'


def configure(parser) -> None:
    """Start the HDP graph (sim bridge, planner, controller) as processes; Ctrl-C stops it."""
    parser.add_argument('--params-file', type=Path, default=None,
                        help=f'node parameters (default: {default_params_file()})')
    parser.add_argument('--nodes', default=','.join(NODES),
                        help='comma-separated nodes to start (default: all three; '
                             'planner_node,controller_node for a real robot)')
    parser.add_argument('-p', '--param', action='append', default=[], metavar='NODE:NAME:=VALUE',
                        help='override one parameter, e.g. controller_node:method:=planner (repeatable)')
    parser.set_defaults(func=run)


def node_commands(nodes: list[str], params_file: Path, overrides: list[str]) -> dict[str, list[str]]:
    """node -> the command line that starts it with this Python, its parameters and overrides."""
    unknown = [n for n in nodes if n not in NODES]
    if unknown or not nodes:
        raise ValueError(f'unknown node(s) {unknown}; nodes: {", ".join(NODES)}')
    commands = {n: [sys.executable, '-m', f'{NODES[n]}.{n}', '--ros-args', '--params-file', str(params_file)]
                for n in nodes}
    for override in overrides:
        node, _, assignment = override.partition(':')
        if node not in NODES or ':=' not in assignment:
            raise ValueError(f'--param takes NODE:NAME:=VALUE with NODE one of {", ".join(NODES)}, got {override!r}')
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
    env = dict(os.environ if env is None else env, PYTHONUNBUFFERED='1')
    procs = {}
    try:
        for name, command in commands.items():
            procs[name] = subprocess.Popen(command, stdout=output(name), stderr=subprocess.STDOUT, text=True,
                                           env=env, start_new_session=True)
            say(f'started {name} (pid {procs[name].pid})')
        yield procs
    finally:
        stop_nodes(procs, say)


def run(args) -> int:
    params_file = args.params_file or default_params_file()
    if not params_file.is_file():
        print(f'hdp launch: no parameter file {params_file}', file=sys.stderr)
        return 2
    try:
        commands = node_commands([n.strip() for n in args.nodes.split(',') if n.strip()], params_file, args.param)
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

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    relays = []
    try:
        with running_nodes(commands, lambda name: subprocess.PIPE, say) as procs:
            for name, proc in procs.items():
                relays.append(threading.Thread(target=_relay, args=(name, proc.stdout, lock), daemon=True))
                relays[-1].start()
            died = None
            while died is None and not stop.wait(0.2):
                died = next((name for name, p in procs.items() if p.poll() is not None), None)
            if died is not None:
                say(f'{died} exited with code {procs[died].returncode}; stopping the other nodes')
            else:
                say(f'{requested[0]}: stopping the nodes')
    finally:
        for relay in relays:
            relay.join(timeout=2.0)
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    codes = {name: p.returncode for name, p in procs.items()}
    if died is not None:
        return codes[died] if codes[died] > 0 else 1
    failed = {n: c for n, c in codes.items() if c != 0}
    if failed:
        say(f'nodes that did not exit cleanly: {failed}')
    return 1 if failed else 0
