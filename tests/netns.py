"""Two hosts on one machine, for tests: hdp_bringup.netns, skipping where namespaces cannot be made.

    with netns.two_hosts(rate_mbit=100) as (robot, workstation):
        talker = robot.popen([sys.executable, 'talker.py'], env=env)
        workstation.run([sys.executable, 'listener.py'], env=env, timeout=30)

Where namespaces cannot be made (not root, no iproute2, no permission) the test is skipped
with the reason.
"""

import contextlib

import pytest

from hdp_bringup.netns import Host, NamespacesUnavailable, discovery_env  # noqa: F401 (the tests use them)
from hdp_bringup import netns


@contextlib.contextmanager
def two_hosts(rate_mbit: float | None = None):
    """(robot, workstation), as hdp_bringup.netns.two_hosts; pytest.skip where it cannot make them."""
    try:
        with netns.two_hosts(rate_mbit) as hosts:
            yield hosts
    except NamespacesUnavailable as why:
        pytest.skip(str(why))
