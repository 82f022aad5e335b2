"""`hdp bench transport`, briefly and small: every mode runs and its frames arrive.

Timing figures depend on the machine and its load, so none is asserted.
"""

import json
import subprocess
import sys

import pytest

from hdp_tools.transport_bench import MODES, STREAMS

pytestmark = pytest.mark.dds

HDP = [sys.executable, '-m', 'hdp_tools.cli.main', 'bench', 'transport']


def test_every_mode_receives_all_four_streams(ros_domain):
    result = subprocess.run([*HDP, '--seconds', '1', '--width', '64', '--height', '48', '--json',
                             '--domain-id', str(ros_domain)], text=True, capture_output=True, timeout=180)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report['image'] == '64x48' and report['domain_id'] == ros_domain
    assert list(report['results']) == list(MODES)
    for mode, figures in report['results'].items():
        assert set(figures['streams']) == set(STREAMS)
        for topic, stream in figures['streams'].items():
            assert stream['received'] > 0, f'{mode}: nothing arrived on {topic}'
        assert figures['latency_p99_ms'] is not None and figures['throughput_mb_s'] > 0
        assert set(figures['targets']) == {'min_hz >= 30', 'p99 <= 30 ms'}
    assert report['throughput_ratio_rclpy_vs_raw'] is not None
    assert result.stderr.count('bench transport:') == len(MODES)   # a progress line per mode


def test_table_and_mode_selection(ros_domain):
    result = subprocess.run([*HDP, '--seconds', '0.5', '--width', '64', '--height', '48', '--modes', 'raw',
                             '--domain-id', str(ros_domain)], text=True, capture_output=True, timeout=120)
    assert result.returncode == 0, result.stderr
    rows = [line for line in result.stdout.splitlines() if line.startswith('| ')]
    assert rows[0].startswith('| mode |') and [r.split(' | ')[0] for r in rows[1:]] == ['| raw']
    result = subprocess.run([*HDP, '--modes', 'ours'], text=True, capture_output=True, timeout=60)
    assert result.returncode == 2 and 'unknown mode(s) ours' in result.stderr
