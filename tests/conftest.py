"""Shared fixtures: every test that touches DDS gets a domain of its own."""

import itertools
import os
import random
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))   # tests import dds_procs

# Spread over 1..199 from a per-run random start so parallel runs rarely meet;
# discovery is localhost-only, so runs on other machines never do.
_domains = itertools.count(random.Random(os.getpid()).randrange(200))


@pytest.fixture
def ros_domain() -> int:
    return 1 + next(_domains) % 199
