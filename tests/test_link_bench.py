"""`hdp bench link`: its statistics, table and episode comparison, the namespaces' environment,
and a short run across two network namespaces."""

import json
import os
import subprocess
import sys
import time

import pytest

from hdp_bringup import link_bench, link_episodes, link_streams, netns
from hdp_tools.cli import main as hdp_main

pytestmark = pytest.mark.unit

MS = 1_000_000       # ns


def test_stream_stats_count_each_published_frame_once_and_ignore_the_warm_up():
    stamps = [i * 33 * MS for i in range(10)]                 # 10 frames in a 0.33 s window
    arrivals = [[s, s + (5 + i) * MS] for i, s in enumerate(stamps) if i not in (3, 7)]
    arrivals += [[stamps[0], stamps[0] + 99 * MS],            # a duplicate: the first arrival counts
                 [-33 * MS, 0]]                               # a warm-up frame: not in the window
    stats = link_bench.stream_stats(stamps, arrivals, 0.33)
    ages = stats.pop('ages_ms')
    assert sorted(ages) == [5.0, 6.0, 7.0, 9.0, 10.0, 11.0, 13.0, 14.0]
    assert stats == {'published': 10, 'received': 8, 'lost': 2, 'hz': round(8 / 0.33, 2),
                     'age_p50_ms': 9.5, 'age_p95_ms': 13.65}


def test_stream_stats_of_a_stream_that_never_arrived():
    stats = link_bench.stream_stats([0, 33 * MS], [], 1.0)
    assert stats['received'] == 0 and stats['lost'] == 2 and stats['hz'] == 0.0
    assert stats['age_p50_ms'] is None and stats['age_p95_ms'] is None


def published(stamps, cpu_s=0.5, elapsed_s=1.0, payload=1000):
    return {'stamps_ns': stamps, 'rate_hz': 30.0, 'window_s': 1.0, 'elapsed_s': elapsed_s, 'cpu_s': cpu_s,
            'encode_ms': {'jpeg': [1.0, 2.0, 3.0], 'png': []},
            'payload_bytes': dict.fromkeys(link_streams.STREAMS, payload * len(stamps))}


def test_camera_report_pools_the_streams_and_takes_the_slowest():
    stamps = [i * 33 * MS for i in range(30)]
    arrivals = {stream: [[s, s + 10 * MS] for s in stamps] for stream in link_streams.STREAMS}
    arrivals['side/depth'] = arrivals['side/depth'][:27]         # 3 lost on one stream
    report = link_bench.camera_report(100.0, 'compressed', published(stamps), {'arrivals': arrivals}, 2_500_000, 7)
    assert report['published_hz'] == 30.0 and report['min_hz'] == 27.0
    assert report['lost'] == 3 and report['published'] == 120
    assert report['age_p50_ms'] == 10.0 and report['age_p95_ms'] == 10.0
    assert report['link_mbit_s'] == 20.0                  # 2.5 MB over the 1 s it took
    assert report['udp_receive_buffer_drops'] == 7
    assert report['publisher_cpu_percent'] == 50.0
    assert report['encode_ms'] == {'jpeg': {'p50': 2.0, 'p95': 2.9, 'frames': 3}}     # no PNG encoded
    assert report['streams']['front/color']['payload_kb'] == 1.0
    assert report['payload_mbit_s_at_rate'] == 1.0        # 4 streams x 1 kB x 30 Hz: 0.96 Mbit/s
    assert set(report['streams']) == set(link_streams.STREAMS)
    json.dumps(report)                                    # --json prints it as it is


def configuration(link, transport, min_hz=30.0, cpu=10.0, lost=0):
    return {'link_mbit': link, 'transport': transport, 'published_hz': 30.0, 'min_hz': min_hz, 'lost': lost,
            'published': 1200, 'age_p50_ms': 12.3, 'age_p95_ms': 45.6, 'link_mbit_s': 60.2,
            'payload_mbit_s_at_rate': 70.1, 'udp_receive_buffer_drops': 12,
            'publisher_cpu_percent': cpu, 'encode_ms': {'jpeg': {'p50': 0.9, 'p95': 1.1, 'frames': 600}}
            if transport == 'compressed' else {}, 'streams': {}}


def test_the_goal_is_every_stream_at_30_hz_over_100_mbit_compressed():
    assert link_bench.goal([configuration(100.0, 'compressed', min_hz=29.9)])['met'] is True
    assert link_bench.goal([configuration(100.0, 'compressed', min_hz=28.0)])['met'] is False
    assert link_bench.goal([configuration(1000.0, 'compressed')])['met'] is None      # not measured
    assert link_bench.compression_cost([configuration(100.0, 'raw', cpu=5.0),
                                        configuration(100.0, 'compressed', cpu=45.5),
                                        configuration(1000.0, 'raw')]) == {'100': 40.5}


def report(episodes=None):
    settings = {'width': 640, 'height': 480, 'rate_hz': 30.0, 'seconds': 10.0, 'warmup_s': 2.0,
                'discovery': 'subnet', 'frames': 4, 'sensor_profile': 'd415', 'jpeg_quality': 95, 'png_level': 3}
    configurations = [configuration(100.0, 'raw', min_hz=4.0, lost=3), configuration(100.0, 'compressed', cpu=60.0)]
    return link_bench.summarise(settings, configurations, episodes,
                                {'cpus': 2, 'load_1min_before': 3.5, 'load_1min_after': 3.9})


def test_the_table_has_a_row_per_configuration_and_says_whether_the_goal_is_met():
    text = link_bench.format_report(report())
    lines = text.splitlines()
    assert lines[0].startswith('2 cameras x (rgb8 colour + 16UC1 depth) at 640x480, 30 Hz; 4 frame(s)')
    assert 'load (1 min) 3.5 before, 3.9 after' in lines[1]
    assert '| 100 Mbit/s | raw | 30.0 | 4.0 | 3/1200 | 12 | 12.3 / 45.6 | 60.2 | 70.1 | 10% | - |' in lines
    assert ('| 100 Mbit/s | compressed | 30.0 | 30.0 | 0/1200 | 12 | 12.3 / 45.6 | 60.2 | 70.1 | 60% '
            '| JPEG 0.9 / 1.1 |') in lines
    assert ('goal, 30 Hz of both cameras at the workstation over 100 Mbit/s compressed: met '
            '(slowest stream 30.0 Hz, lost 0/1200)') in lines
    assert 'compression on the robot host at 100 Mbit/s: +50% of a core (publisher CPU, compressed minus raw)' in lines
    assert link_bench.progress_line(configuration(100.0, 'raw')).startswith(
        '100 Mbit/s raw: published 30.0 Hz, arrived 30.0 Hz (slowest stream), lost 0/1200 (12 datagrams dropped '
        'at a full receive buffer), age p50 12.3 / p95 45.6 ms')


def test_episodes_compare_success_per_task_and_name_the_seeds_that_differ():
    def run(outcomes, problem=None):
        return {'episodes': [{'task': task, 'seed': seed, 'outcome': outcome, 'reason': '',
                              'success': outcome == 'succeeded', 'wall_s': 5.0}
                             for (task, seed), outcome in outcomes.items()], 'problem': problem}
    one_host = run({('reach_target', 1000): 'succeeded', ('reach_target', 1001): 'succeeded',
                    ('open_drawer', 1000): 'failed', ('open_drawer', 1001): 'succeeded'})
    split = run({('reach_target', 1000): 'succeeded', ('reach_target', 1001): 'failed',
                 ('open_drawer', 1000): 'failed'}, problem='the scene of seed 1001 did not come up')
    episodes = link_episodes.episode_comparison(['reach_target', 'open_drawer'], 2, 100.0, one_host, split)
    assert episodes['tasks'] == {'reach_target': {'episodes': 2, 'one_host': 2, 'split': 1},
                                 'open_drawer': {'episodes': 2, 'one_host': 1, 'split': 0}}
    assert episodes['differ'] == ['open_drawer 1001 (one host succeeded, split not run)',
                                  'reach_target 1001 (one host succeeded, split failed)']
    lines = link_bench.format_report(report(episodes)).splitlines()
    assert '| reach_target | 2/2 | 1/2 |' in lines and '| open_drawer | 1/2 | 0/2 |' in lines
    assert 'split: the scene of seed 1001 did not come up' in lines


def test_ticks_keep_their_schedule_and_drop_what_falls_a_period_behind():
    published_ticks = []
    stamps = link_streams.run_ticks(lambda tick, stamp: published_ticks.append(tick), 20.0, 0.25)
    assert len(stamps) == 5 and published_ticks == [0, 1, 2, 3, 4]
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    slow = link_streams.run_ticks(lambda tick, stamp: time.sleep(0.025), 100.0, 0.1)   # 2.5 periods each
    assert 1 <= len(slow) < 10


def test_each_host_discovers_the_other_as_asked_without_the_parent_s_fast_dds_setup():
    peer = netns.Host('ns', 'veth', '10.213.7.2')
    inherited = {'PATH': '/bin', 'FASTRTPS_DEFAULT_PROFILES_FILE': '/tmp/p.xml', 'ROS_STATIC_PEERS': 'x',
                 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SYSTEM_DEFAULT'}
    subnet = netns.discovery_env('subnet', 7, peer, inherited)
    assert subnet == {'PATH': '/bin', 'ROS_DOMAIN_ID': '7', 'PYTHONUNBUFFERED': '1',
                      'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET'}
    static = netns.discovery_env('static_peers', 7, peer, inherited)
    assert static['ROS_STATIC_PEERS'] == '10.213.7.2' and 'ROS_AUTOMATIC_DISCOVERY_RANGE' not in static
    assert 'ROS_STATIC_PEERS' not in netns.discovery_env('localhost', 7, peer, inherited)


def test_without_root_the_namespaces_are_refused_with_the_reason(monkeypatch):
    monkeypatch.setattr(os, 'geteuid', lambda: 1000)
    with pytest.raises(netns.NamespacesUnavailable, match='network namespaces need root'):
        with netns.two_hosts():
            pass


def test_the_bench_refuses_bad_arguments_and_a_machine_without_namespaces(monkeypatch, tmp_path, capsys):
    out = tmp_path / 'out'
    for args in (['--tasks', 'make_tea'], ['--transports', 'raw,zip'], ['--links', '0'], ['--png-level', '10']):
        assert hdp_main.main(['bench', 'link', '--out', str(out), *args]) == 2
        assert capsys.readouterr().err.startswith('hdp bench link: '), args
    monkeypatch.setattr(netns, 'unavailable', lambda: 'network namespaces need root')
    assert hdp_main.main(['bench', 'link', '--out', str(out)]) == 2
    assert capsys.readouterr().err == 'hdp bench link: cannot make the two hosts: network namespaces need root\n'
    assert not out.exists()


@pytest.mark.dds
@pytest.mark.timeout(300)
def test_a_short_run_across_two_namespaces_reports_every_configuration(tmp_path):
    reason = netns.unavailable()
    if reason:
        pytest.skip(reason)
    done = subprocess.run([sys.executable, '-m', 'hdp_tools.cli.main', 'bench', 'link', '--seconds', '2',
                           '--warmup', '1', '--width', '160', '--height', '120', '--frames', '2', '--json',
                           '--out', str(tmp_path / 'out')], capture_output=True, text=True, timeout=280)
    if done.returncode == 2 and 'cannot make the two hosts' in done.stderr:
        pytest.skip(done.stderr.strip())
    assert done.returncode == 0, done.stderr[-3000:]
    report = json.loads(done.stdout)
    rows = {(c['link_mbit'], c['transport']): c for c in report['cameras']}
    assert set(rows) == {(1000.0, 'raw'), (1000.0, 'compressed'), (100.0, 'raw'), (100.0, 'compressed')}
    for c in rows.values():
        assert set(c['streams']) == set(link_streams.STREAMS)
        assert 0 < c['published'] <= 4 * 60 and c['lost'] < c['published']     # 2 s at 30 Hz, 4 streams
        assert c['age_p50_ms'] is not None and c['link_mbit_s'] > 0 and c['publisher_cpu_percent'] > 0
        assert c['udp_receive_buffer_drops'] >= 0
    for link in (1000.0, 100.0):
        assert rows[(link, 'compressed')]['link_mbit_s'] < rows[(link, 'raw')]['link_mbit_s']
        assert set(rows[(link, 'compressed')]['encode_ms']) == {'jpeg', 'png'}
        assert rows[(link, 'raw')]['encode_ms'] == {}
    assert report['goal']['met'] in (True, False) and report['episodes'] is None
    assert '[link] 100 Mbit/s compressed: published' in done.stderr     # a progress line per measurement
