"""Every `hdp` subcommand and every node executable answers --help, and commands that do not
simulate neither load PyBullet nor print its banner."""

import subprocess
import sys
from importlib.metadata import entry_points

import pytest

from hdp_tools.cli import main

pytestmark = pytest.mark.dds

COMMANDS = sorted(tuple(e.name.split('.')) for e in entry_points(group='hdp.commands'))
NODES = {'hdp_planner.planner_node': 'planner_node', 'hdp_controller.controller_node': 'controller_node',
         'hdp_sim_bridge.sim_bridge_node': 'sim_bridge_node'}


@pytest.mark.unit
def test_every_hdp_command_has_help(capsys):
    assert len(COMMANDS) >= 15
    for path in [(), *sorted({c[:1] for c in COMMANDS}), *COMMANDS]:
        with pytest.raises(SystemExit) as exited:
            main.main([*path, '--help'])
        out = capsys.readouterr().out
        assert exited.value.code == 0, path
        assert out.startswith(f"usage: hdp {' '.join(path)}".rstrip()), (path, out[:200])


@pytest.mark.parametrize('path', [('topic', 'echo'), ('node', 'list'), ('bench', 'transport'),
                                  ('train', 'low-level'), ('train', 'high-level')])
def test_commands_that_do_not_simulate_load_no_simulator(path):
    probe = ('import sys; from hdp_tools.cli import main\n'
             f'try:\n    main.main({list(path) + ["--help"]!r})\nexcept SystemExit:\n    pass\n'
             'print("pybullet" in sys.modules)')
    result = subprocess.run([sys.executable, '-c', probe], capture_output=True, text=True, timeout=120)
    assert result.stdout.strip().endswith('False'), result.stdout[-300:]
    assert 'pybullet build time' not in result.stderr


@pytest.mark.parametrize('module, name', NODES.items())
def test_node_executables_print_their_parameters(module, name):
    result = subprocess.run([sys.executable, '-m', module, '--help'], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(f'usage: {name} [--ros-args') and '\nparameters:\n' in result.stdout
    node_class = next(v for k, v in vars(__import__(module, fromlist=['x'])).items()
                      if isinstance(v, type) and k.endswith('Node') and getattr(v, 'PARAMETERS', None))
    for parameter in node_class.PARAMETERS:
        assert f'\n  {parameter} (default ' in result.stdout


def test_the_old_module_path_says_where_the_command_went():
    """Published command lines ran `python -m hdp_msgs_py.cli.main ...` (torchrun too): they get one
    line naming the new homes and exit 2, not a traceback."""
    result = subprocess.run([sys.executable, '-m', 'hdp_msgs_py.cli.main', 'eval', 'hierarchy', '--help'],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and result.stdout == ''
    assert result.stderr == ("hdp_msgs_py.cli.main moved: run 'hdp ...' or 'python -m hdp_tools.cli.main ...'\n")
