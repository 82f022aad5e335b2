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
