"""Shared fixtures: every test that touches DDS gets a domain of its own."""

import itertools
import os
import random
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))   # tests import dds_procs

# HDP_HIDE_ROS=1 runs tests as on a machine without ROS 2 (test_without_ros.py does).
ROS_PACKAGES = ('rclpy', 'builtin_interfaces', 'std_msgs', 'geometry_msgs', 'sensor_msgs', 'trajectory_msgs',
                'tf2_msgs', 'rosgraph_msgs', 'control_msgs')
if os.environ.get('HDP_HIDE_ROS') == '1':
    sys.modules.update(dict.fromkeys(ROS_PACKAGES))      # `import rclpy` raises ImportError

# Spread over 1..199 from a per-run random start so parallel runs rarely meet;
# discovery is localhost-only, so runs on other machines never do.
_domains = itertools.count(random.Random(os.getpid()).randrange(200))


@pytest.fixture
def ros_domain() -> int:
    return 1 + next(_domains) % 199


# Test tiers (pytest.ini): every test is exactly one of these. A file sets its dominant tier with
# `pytestmark = pytest.mark.<tier>`; a test of another tier in it carries its own decorator.
TIERS = ('unit', 'sim', 'dds')


@pytest.hookimpl(tryfirst=True)      # before `-m` deselects: it must see one tier per test
def pytest_collection_modifyitems(config, items):
    """Give each test its closest tier marker only (a test's own overrides its class's and its
    module's), so `-m unit` never picks a test its file marks unit but it marks sim; refuse to
    run when a test has none."""
    untiered, chosen = [], {}
    for item in items:
        closest = next((m.name for m in item.iter_markers() if m.name in TIERS), None)
        own = {m.name for m in item.own_markers if m.name in TIERS}
        if closest is None or len(own) > 1:
            untiered.append(f'  {item.nodeid}' + (f' (marked {" and ".join(sorted(own))})' if own else ''))
        chosen[item] = closest
    if untiered:
        raise pytest.UsageError(
            f'{len(untiered)} test(s) without exactly one tier marker ({", ".join(TIERS)}; see pytest.ini):\n'
            + '\n'.join(untiered) + '\nAdd `pytestmark = pytest.mark.<tier>` to the file or decorate the test.')
    for item, tier in chosen.items():
        for node in item.listchain()[:-1]:          # the module's and class's tier markers go...
            node.own_markers[:] = [m for m in node.own_markers if m.name not in TIERS]
        if tier not in {m.name for m in item.own_markers}:
            item.add_marker(tier)                   # ...onto each test that did not choose its own


def pytest_sessionfinish(session):
    """Processes the tests SIGKILL leave their Fast DDS shared memory behind; each process start
    (ros.init) removes what dead ones left, and this what the run's last ones left."""
    from hdp_ros import shm
    shm.remove_dead_segments()
