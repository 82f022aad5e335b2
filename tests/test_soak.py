"""`hdp bench soak`: the fault schedule, memory accounting, and a short soak of the real graph
with every fault injected once."""

import json
import os
import subprocess
import sys

import pytest

from hdp_bringup import soak

pytestmark = pytest.mark.dds


@pytest.mark.unit
def test_one_fault_in_every_n_episodes_in_turn():
    schedule = [soak.fault_of(i, 10) for i in range(80)]
    assert [(i, f) for i, f in enumerate(schedule) if f] == [
        (9, 'camera_stop'), (19, 'controller_kill'), (29, 'bad_nbp'), (39, 'bad_reset'),
        (49, 'camera_stop'), (59, 'controller_kill'), (69, 'bad_nbp'), (79, 'bad_reset')]
    assert [soak.fault_of(i, 1) for i in range(5)] == [*soak.FAULTS, 'camera_stop']


@pytest.mark.unit
def test_rss_is_read_from_proc_and_growth_is_relative(tmp_path):
    assert 1.0 < soak.rss_mib(os.getpid()) < 100_000
    (tmp_path / '7').mkdir()
    (tmp_path / '7' / 'status').write_text('Name:\tpython3\nVmRSS:\t  204800 kB\nThreads:\t3\n')
    assert soak.rss_mib(7, tmp_path) == 200.0 and soak.rss_mib(8, tmp_path) is None
    memory = soak.memory_report({'a': 200.0, 'b': 100.0, 'c': None}, {'a': 210.0, 'b': 90.0, 'c': 50.0})
    assert memory == {'a': {'start_mib': 200.0, 'end_mib': 210.0, 'growth_percent': 5.0},
                      'b': {'start_mib': 100.0, 'end_mib': 90.0, 'growth_percent': -10.0}}


def test_bad_arguments_exit_2_before_anything_starts(tmp_path, ros_domain):
    for args in (('--tasks', 'make_tea'), ('--episodes', '0'), ('--fault-every', '0'), ('-p', 'nobody:x:=1')):
        proc = subprocess.run([sys.executable, '-m', 'hdp_tools.cli.main', 'bench', 'soak', '--out',
                               str(tmp_path / 'out'), *args], capture_output=True, text=True, timeout=60,
                              env=dict(os.environ, ROS_DOMAIN_ID=str(ros_domain)))
        assert proc.returncode == 2 and proc.stderr.startswith('hdp bench soak: '), (args, proc.stderr)
    assert not (tmp_path / 'out').exists()


@pytest.mark.timeout(900)
def test_a_short_soak_reports_every_fault_with_its_cause(tmp_path, ros_domain):
    out = tmp_path / 'soak'
    proc = subprocess.run([sys.executable, '-m', 'hdp_tools.cli.main', 'bench', 'soak', '--episodes', '4',
                           '--fault-every', '1', '--tasks', 'reach_target', '--out', str(out),
                           '-p', 'sim_bridge_node:camera_width:=128', '-p', 'sim_bridge_node:camera_height:=96'],
                          capture_output=True, text=True, timeout=840,
                          env=dict(os.environ, ROS_DOMAIN_ID=str(ros_domain), OMP_NUM_THREADS='1'))
    report = json.loads((out / 'soak.json').read_text())
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert [f['fault'] for f in report['faults']] == list(soak.FAULTS)
    assert all(f['reported'] for f in report['faults']), report['faults']
    camera = report['episodes'][0]
    assert camera['outcome'] == 'failed' and 'camera side timed out' in camera['reason']
    assert report['unexpected_exits'] == [] and report['controller_restarts'] == 1
    processes = {*soak.NODES, 'lifecycle_manager'}
    assert set(report['memory']) == processes     # the restarted controller measured from episode 3
    assert all(set(e['rss_mib']) == processes for e in report['episodes'])     # the trend, per episode
    assert any('rejected reset: reach_target has variations 0..' in line for line in report['refusals'])
    assert 'faults reported with their cause: 4/4' in proc.stdout


def test_a_restarted_node_joins_the_graphs_domain_not_the_callers(tmp_path, monkeypatch, ros_domain):
    import rclpy

    from hdp_bringup.demo import watcher
    monkeypatch.setenv('ROS_DOMAIN_ID', str(ros_domain + 1))        # not the graph's: the soak picked its own
    command = [sys.executable, '-c', 'import os, time; print(os.environ["ROS_DOMAIN_ID"], flush=True); time.sleep(60)']
    log = tmp_path / 'sleeper.log'
    with watcher.watched_graph({'sleeper': command}, tmp_path, ros_domain, lambda: rclpy.create_node('soak_test'),
                               lambda line: None) as session:
        first = session.procs['sleeper']
        assert session.spin_until(lambda: log.exists() and log.read_text().count('\n') == 1, 30.0)
        session.restart('sleeper')
        assert first.returncode is not None and session.procs['sleeper'] is not first
        assert session.spin_until(lambda: log.read_text().count('\n') == 2, 30.0)
    assert log.read_text().splitlines()[:2] == [str(ros_domain)] * 2     # then the stop's KeyboardInterrupt
