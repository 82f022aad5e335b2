"""The dependency rule (ARCHITECTURE.md): robot-side nodes load neither the simulator nor a
planning library they do not use, and every package declares exactly the HDP packages it imports."""

import ast
import json
import subprocess
import sys
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / 'src'
PACKAGES = sorted(p.name for p in SRC.iterdir() if (p / 'package.xml').is_file())
SIMULATION = ('pybullet', 'ompl', 'hdp_sim_bridge')


@pytest.mark.parametrize('load', [
    'import hdp_planner.planner_node as n; n.NextBestPoseAgent.from_checkpoint(n.default_checkpoint())',
    'import hdp_controller.controller_node as n; n.load_policy("rkd", sampler="ddim")'])
def test_robot_side_nodes_load_no_simulator_and_no_planner(load):
    """Each node's module imported and its model loaded, as the node does at start-up."""
    probe = f'import json, sys; {load}; print(json.dumps(sorted(m for m in {SIMULATION!r} if m in sys.modules)))'
    result = subprocess.run([sys.executable, '-c', probe], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout.splitlines()[-1]) == []


def test_the_planning_baselines_plan_on_the_robot_without_the_simulator():
    """controller_node with method planner plans in PyBullet with OMPL, but in a kinematic scene of
    its own: the simulator package stays unloaded."""
    probe = ('import json, sys; import numpy as np; from hdp_controller.policy import load_policy; '
             'from hdp_controller.baselines import standalone_scene; standalone_scene(); '
             'load_policy("planner"); print(json.dumps(sorted(m for m in ("pybullet", "ompl", "hdp_sim_bridge") '
             'if m in sys.modules)))')
    result = subprocess.run([sys.executable, '-c', probe], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout.splitlines()[-1]) == ['ompl', 'pybullet']


def _hdp_imports(package: str) -> set[str]:
    """Top-level hdp_* packages that ``package``'s code imports (module level or inside functions)."""
    found = set()
    for path in (SRC / package / package).rglob('*.py'):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module]
            else:
                continue
            found.update(n.split('.')[0] for n in names if n.startswith('hdp_'))
    return found - {package}


def _setup_requires(package: str) -> set[str]:
    tree = ast.parse((SRC / package / 'setup.py').read_text())
    call = next(n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, 'id', '') == 'setup')
    requires = next(k.value for k in call.keywords if k.arg == 'install_requires')
    return {r for r in ast.literal_eval(requires) if r.startswith('hdp_')}


@pytest.mark.parametrize('package', PACKAGES)
def test_declared_hdp_dependencies_are_the_imported_ones(package):
    """Imported ones, plus, for hdp_bringup, the packages whose node executables it starts."""
    from hdp_bringup.launch_cli import NODES
    root = ElementTree.parse(SRC / package / 'package.xml').getroot()
    declared = {e.text for e in root.findall('exec_depend') if e.text.startswith('hdp_')}
    imported = _hdp_imports(package) | (set(NODES.values()) if package == 'hdp_bringup' else set())
    assert declared == imported, f'package.xml of {package}: declares {sorted(declared)}, imports {sorted(imported)}'
    assert _setup_requires(package) == imported, f'setup.py of {package}'
