"""The dependency rule (ARCHITECTURE.md): robot-side nodes load neither the simulator nor a
planning library they do not use, every package imports only the HDP packages the layering lets it
(MAY_IMPORT), and every package declares exactly the HDP packages it imports."""

import ast
import json
import subprocess
import sys
import xml.etree.ElementTree as ElementTree
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

SRC = Path(__file__).resolve().parents[1] / 'src'
PACKAGES = sorted(p.name for p in SRC.iterdir() if (p / 'package.xml').is_file())
SIMULATION = ('pybullet', 'ompl', 'hdp_sim_bridge')

# Who may import whom (ARCHITECTURE.md, "Packages and seams"). Infrastructure first: hdp_motion and
# hdp_learning are leaves, hdp_msgs_py sits on hdp_motion, hdp_ros and hdp_data on hdp_msgs_py;
# hdp_tools (the `hdp` command) uses infrastructure only and no package imports it (subcommands
# arrive through the hdp.commands entry points). The robot side and the simulator use infrastructure
# and never each other; hdp_eval and hdp_bringup put them together.
INFRASTRUCTURE = {'hdp_motion', 'hdp_msgs_py', 'hdp_ros', 'hdp_data', 'hdp_learning'}
SIDES = {'hdp_planner', 'hdp_controller', 'hdp_sim_bridge'}
MAY_IMPORT = {
    'hdp_motion': set(),
    'hdp_learning': set(),
    'hdp_msgs_py': {'hdp_motion'},
    'hdp_ros': {'hdp_msgs_py'},
    'hdp_data': {'hdp_motion', 'hdp_msgs_py'},
    'hdp_tools': INFRASTRUCTURE,
    'hdp_planner': INFRASTRUCTURE,
    'hdp_controller': INFRASTRUCTURE,
    'hdp_sim_bridge': INFRASTRUCTURE,
    'hdp_eval': INFRASTRUCTURE | SIDES,
    'hdp_bringup': INFRASTRUCTURE | SIDES,
}
# Importing these loads no torch (hdp_learning imports it inside its functions only).
TORCH_FREE = ('hdp_msgs_py', 'hdp_ros', 'hdp_data', 'hdp_learning', 'hdp_tools')


@pytest.mark.dds
@pytest.mark.parametrize('load', [
    'import hdp_planner.planner_node as n; n.NextBestPoseAgent.from_checkpoint(n.default_checkpoint())',
    'import hdp_controller.controller_node as n; n.load_policy("rkd", sampler="ddim")'])
def test_robot_side_nodes_load_no_simulator_and_no_planner(load):
    """Each node's module imported and its model loaded, as the node does at start-up."""
    probe = f'import json, sys; {load}; print(json.dumps(sorted(m for m in {SIMULATION!r} if m in sys.modules)))'
    result = subprocess.run([sys.executable, '-c', probe], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout.splitlines()[-1]) == []


@pytest.mark.dds
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


@pytest.mark.unit
def test_every_package_has_a_place_in_the_layering():
    assert sorted(MAY_IMPORT) == PACKAGES


@pytest.mark.unit
@pytest.mark.parametrize('package', PACKAGES)
def test_packages_import_only_what_the_layering_allows(package):
    forbidden = _hdp_imports(package) - MAY_IMPORT.get(package, set())
    assert not forbidden, f'{package} imports {sorted(forbidden)}; it may import {sorted(MAY_IMPORT.get(package, ()))}'


@pytest.mark.dds
def test_the_infrastructure_packages_import_no_torch():
    """Every module of the packages messages, nodes' helpers, data, learning rules and the `hdp`
    command come from, imported in a fresh process: torch stays unloaded."""
    probe = ('import importlib, pkgutil, sys\n'
             f'for name in {TORCH_FREE!r}:\n'
             '    package = importlib.import_module(name)\n'
             '    for module in pkgutil.walk_packages(package.__path__, name + "."):\n'
             '        importlib.import_module(module.name)\n'
             'print(sorted(m for m in ("torch", "pybullet") if m in sys.modules))')
    result = subprocess.run([sys.executable, '-c', probe], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[-1] == '[]', result.stdout[-500:]


@pytest.mark.unit
@pytest.mark.parametrize('node, attribute, logic', [
    ('hdp_planner/hdp_planner/planner_node.py', 'loop', 'hdp_planner.planner_logic:PlannerLoop'),
    ('hdp_controller/hdp_controller/controller_node.py', 'logic', 'hdp_controller.segment_controller:SegmentController')])
def test_nodes_only_call_their_logic_never_read_its_fields(node, attribute, logic):
    """The node/logic contract is the logic's methods and the records they return: a node that
    reads or sets a field of its logic object (``self.logic.running``) depends on its insides."""
    import importlib
    module, name = logic.split(':')
    cls = getattr(importlib.import_module(module), name)
    used = {n.attr for n in ast.walk(ast.parse((SRC / node).read_text()))
            if isinstance(n, ast.Attribute) and isinstance(n.value, ast.Attribute) and n.value.attr == attribute
            and isinstance(n.value.value, ast.Name) and n.value.value.id == 'self'}
    assert used, f'{node} does not use self.{attribute}'
    fields = sorted(a for a in used if not callable(getattr(cls, a, None)))
    assert not fields, f'{node} reaches into {name}: {fields}'
