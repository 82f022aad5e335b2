"""The workspace packaging: the ament_python packages colcon builds without ROS installed,
with package.xml, setup.py and setup.cfg in agreement."""

import ast
import configparser
import json
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / 'src'
PACKAGES = ('hdp_motion', 'hdp_msgs_py', 'hdp_ros', 'hdp_data', 'hdp_learning', 'hdp_tools', 'hdp_planner',
            'hdp_controller', 'hdp_sim_bridge', 'hdp_eval', 'hdp_bringup')
# Packages that need no ROS: the robot model, recorded data, the learning rules.
ROS_FREE = ('hdp_motion', 'hdp_data', 'hdp_learning')
# package -> the node executable `ros2 run <package> <executable>` starts
NODES = {
    'hdp_planner': 'planner_node',
    'hdp_controller': 'controller_node',
    'hdp_sim_bridge': 'sim_bridge_node',
}
# colcon's own entry point; the package has no __main__, so `-m colcon` fails.
COLCON = [sys.executable, '-c',
          'import sys; from colcon_core.command import main; sys.exit(main())']


def _setup_py(pkg):
    """Return (name, console_scripts) that src/<pkg>/setup.py declares."""
    tree = ast.parse((SRC / pkg / 'setup.py').read_text())
    consts = {}
    for node in ast.walk(tree):
        if (isinstance(node, ast.Assign) and len(node.targets) == 1
                and isinstance(node.targets[0], ast.Name)
                and isinstance(node.value, ast.Constant)):
            consts[node.targets[0].id] = node.value.value
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call)
             and isinstance(n.func, ast.Name) and n.func.id == 'setup']
    assert len(calls) == 1, f'{pkg}/setup.py: expected one setup() call'
    kwargs = {kw.arg: kw.value for kw in calls[0].keywords}

    def value(expr):
        if isinstance(expr, ast.Name):
            return consts[expr.id]
        return ast.literal_eval(expr)

    entry_points = value(kwargs['entry_points']) if 'entry_points' in kwargs else {}
    return value(kwargs['name']), entry_points.get('console_scripts', [])


@pytest.mark.parametrize('pkg', PACKAGES)
def test_package_metadata_agrees(pkg):
    root = ET.parse(SRC / pkg / 'package.xml').getroot()
    assert root.tag == 'package' and root.get('format') == '3'
    assert root.findtext('name') == pkg
    assert root.findtext('export/build_type') == 'ament_python'
    assert root.findtext('license') == 'Apache-2.0'
    assert root.findtext('maintainer') == 'HDP-ROS developers'
    exec_depends = {e.text for e in root.findall('exec_depend')}
    if pkg not in ROS_FREE:
        assert 'rclpy' in exec_depends
    assert 'python3-pytest' in {e.text for e in root.findall('test_depend')}

    name, console_scripts = _setup_py(pkg)
    assert name == pkg
    if pkg in NODES:
        exe = NODES[pkg]
        assert f'{exe} = {pkg}.{exe}:main' in console_scripts

    marker = SRC / pkg / 'resource' / pkg
    assert marker.is_file() and marker.stat().st_size == 0

    cfg = configparser.ConfigParser(interpolation=None)
    cfg.read(SRC / pkg / 'setup.cfg')
    assert cfg['develop']['script_dir'] == f'$base/lib/{pkg}'
    assert cfg['install']['install_scripts'] == f'$base/lib/{pkg}'


def test_colcon_meta_names_real_packages():
    meta = json.loads((ROOT / 'colcon.meta').read_text())
    assert set(meta['names']) <= set(PACKAGES)


@pytest.mark.dds
@pytest.mark.timeout(300)
def test_colcon_build_installs_ros_layout(tmp_path):
    ws = tmp_path / 'ws'
    shutil.copytree(SRC, ws / 'src', ignore=shutil.ignore_patterns(
        '__pycache__', '*.egg-info', 'build', 'install', 'log'))
    shutil.copy2(ROOT / 'colcon.meta', ws / 'colcon.meta')

    env = dict(os.environ)
    # No underlay may leak in (a sourced ROS or an older HDP install), and no
    # user-level colcon defaults (e.g. symlink-install) may change the layout.
    for var in ('AMENT_PREFIX_PATH', 'COLCON_PREFIX_PATH', 'COLCON_DEFAULTS_FILE'):
        env.pop(var, None)
    env['COLCON_HOME'] = str(tmp_path / 'colcon_home')

    proc = subprocess.run(
        COLCON + ['--log-base', 'log', 'build', '--base-paths', 'src',
                  '--event-handlers', 'desktop_notification-', 'terminal_title-'],
        cwd=ws, env=env, capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, f'colcon build failed:\n{proc.stdout}\n{proc.stderr}'

    install = ws / 'install'
    for pkg in PACKAGES:
        share = install / pkg / 'share'
        assert (share / pkg / 'package.xml').is_file(), pkg
        assert (share / 'ament_index' / 'resource_index' / 'packages' / pkg).is_file(), pkg
    for pkg, exe in NODES.items():
        script = install / pkg / 'lib' / pkg / exe
        assert script.is_file(), script
        assert os.access(script, os.X_OK), script
        site = next((install / pkg / 'lib').glob('python3*/site-packages'))
        assert (site / pkg / f'{exe}.py').is_file()
    assert os.access(install / 'hdp_tools' / 'lib' / 'hdp_tools' / 'hdp', os.X_OK)
    site = next((install / 'hdp_ros' / 'lib').glob('python3*/site-packages'))
    assert (site / 'hdp_ros' / 'config' / 'fastdds_localhost.xml').is_file()     # what ros.init() applies

    bringup_share = install / 'hdp_bringup' / 'share' / 'hdp_bringup'
    for launch in ('hdp_graph.launch.py', 'hdp_real_fr3.launch.py'):
        assert (bringup_share / 'launch' / launch).is_file(), launch
    for params in ('hdp_graph.yaml', 'hdp_real_fr3.yaml', 'hdp_fr3_controllers.yaml', 'hdp.rviz',
                   'hdp_foxglove_layout.json'):
        assert (bringup_share / 'config' / params).is_file(), params

    # The ROS interface definitions ship inside hdp_msgs_py (package_data);
    # checked once the Python package itself exists.
    msgs_src = SRC / 'hdp_msgs_py' / 'hdp_msgs_py'
    if (msgs_src / '__init__.py').is_file():
        site = next((install / 'hdp_msgs_py' / 'lib').glob('python3*/site-packages'))
        for msg in msgs_src.glob('interfaces/**/*.msg'):
            assert (site / 'hdp_msgs_py' / msg.relative_to(msgs_src)).is_file(), msg


def test_real_robot_parameters_are_ones_the_nodes_declare():
    """The untested real-robot YAML may only set parameters the sim graph's YAML (exercised by
    the graph tests) sets for the same node (its launch file: tests/test_real_robot.py)."""
    import yaml
    graph = yaml.safe_load((SRC / 'hdp_bringup' / 'config' / 'hdp_graph.yaml').read_text())
    real = yaml.safe_load((SRC / 'hdp_bringup' / 'config' / 'hdp_real_fr3.yaml').read_text())
    assert set(real) == {'planner_node', 'controller_node', 'lifecycle_manager'}
    for node, section in real.items():
        unknown = set(section['ros__parameters']) - set(graph[node]['ros__parameters'])
        assert not unknown, (node, unknown)
