"""/diagnostics: hdp_ros.diagnostics' rate meter, level rule and statuses, and the nodes' arrays
as another process reads them (controller_node and sim_bridge_node).

Run as a script, this file is the reader the process test starts: `python test_diagnostics.py read SECONDS`
prints one JSON line per DiagnosticArray: [[name, level, message], ...].
"""

import json
import os
import select
import signal
import subprocess
import sys
import time
import types

import pytest

from hdp_msgs_py import topics
from hdp_ros import diagnostics
from hdp_ros.liveness import Liveness

pytestmark = pytest.mark.unit


def test_a_rate_meter_counts_arrivals_in_its_window_and_ages_from_the_last():
    meter = diagnostics.RateMeter(started_s=100.0, window_s=5.0)
    assert meter.rate_hz(100.0) == 0.0 and meter.age_s(103.0) == 3.0     # none yet: ages from its start
    for i in range(4):                                                    # 2 Hz for 2 s
        meter.tick(100.5 + 0.5 * i)
    assert meter.rate_hz(102.0) == pytest.approx(2.0)    # since its start, not over a window not yet seen
    assert meter.age_s(102.5) == pytest.approx(0.5)
    for i in range(10):
        meter.tick(102.5 + 0.5 * i)
    assert meter.rate_hz(107.0) == pytest.approx(2.0)    # the last 5 s only
    assert meter.rate_hz(109.0) == pytest.approx(1.2)    # it stopped at 107: the window empties
    assert meter.rate_hz(113.0) == 0.0 and meter.age_s(113.0) == pytest.approx(6.0)


@pytest.mark.parametrize('heard, age, rate, level, message', [
    (True, 0.1, 120.0, diagnostics.OK, '120.0 Hz'),
    (True, 0.4, 120.0, diagnostics.WARN, 'no /joint_states for 0.4 s, expected 10 Hz: is the bridge up?'),
    (True, 6.2, 0.0, diagnostics.ERROR, 'no /joint_states for 6.2 s: is the bridge up?'),
    (False, 6.2, 0.0, diagnostics.ERROR, 'no /joint_states yet (6.2 s): is the bridge up?'),
    (True, 0.05, 4.0, diagnostics.WARN, '/joint_states 4.0 Hz, expected 10 Hz: is the bridge up?'),
])
def test_the_level_rule_errs_past_the_timeout_and_warns_when_late_or_slow(heard, age, rate, level, message):
    assert diagnostics.topic_level('/joint_states', heard, age, rate, 10.0, 5.0, 'is the bridge up?') == \
        (level, message)


def test_a_status_is_named_as_diagnostic_updater_names_them():
    meter = diagnostics.RateMeter(started_s=0.0)
    meter.tick(1.0)
    status = diagnostics.topic_status('planner_node', 'front camera', '/camera/front/color/image_raw', meter, 3.0,
                                      2.0, 5.0, 'is the camera driver running?')
    assert status.name == 'planner_node: front camera' and status.hardware_id == 'planner_node'
    assert status.level == diagnostics.WARN
    assert status.message == ('no /camera/front/color/image_raw for 2.0 s, expected 2 Hz: '
                              'is the camera driver running?')
    assert {v.key: v.value for v in status.values} == {
        'topic': '/camera/front/color/image_raw', 'rate_hz': '0.333', 'age_s': '2.000', 'expected_hz': '2.000',
        'timeout_s': '5.000'}


def test_the_liveness_status_is_the_watchdogs_problem():
    liveness = Liveness(2.0)
    assert diagnostics.liveness_status('controller_node', liveness, 10.0, 1.0).level == diagnostics.OK
    liveness.heard(10.0)
    status = diagnostics.liveness_status('controller_node', liveness, 13.0, 2.0)
    assert status.level == diagnostics.ERROR and status.name == 'controller_node: liveness'
    assert status.message.startswith(f'no {topics.JOINT_STATES} for 3.0 s')


def test_the_planners_loop_summarises_what_runs():
    from hdp_planner.planner_logic import PlannerLoop
    agent = types.SimpleNamespace(read=lambda text: types.SimpleNamespace(grounded=False, text=text))
    loop = PlannerLoop(agent, vocabulary=None, max_segments=4, queue_policy='queue')
    assert loop.summary() == {'instruction': None, 'segments': 0, 'max_segments': 4, 'waiting': 0}
    loop.on_instruction('open the drawer', 0.0)
    loop.on_instruction('close the drawer', 0.0)
    assert loop.summary() == {'instruction': 'open the drawer', 'segments': 0, 'max_segments': 4, 'waiting': 1}


def read(seconds: float) -> None:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from hdp_ros import ros
    ros.init(args=sys.argv)
    node = rclpy.create_node('diagnostics_reader')
    node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, lambda m: print(json.dumps(
        [[s.name, s.level[0], s.message] for s in m.status]), flush=True), topics.DIAGNOSTICS_QOS)
    end = time.monotonic() + seconds
    while rclpy.ok() and time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.1)
    rclpy.try_shutdown()


if __name__ == '__main__' and sys.argv[1:2] == ['read']:
    read(float(sys.argv[2]))


def _until(proc, done, timeout: float) -> list:
    """The arrays the reader prints until done(statuses of one array) or timeout."""
    seen, end = [], time.monotonic() + timeout
    while time.monotonic() < end:
        if not select.select([proc.stdout], [], [], 0.5)[0]:
            continue
        line = proc.stdout.readline()
        if not line:
            break
        seen.append({name: (level, message) for name, level, message in json.loads(line)})
        if done(seen[-1]):
            return seen
    raise AssertionError(f'not seen in {timeout} s; last arrays: {seen[-4:]}')


@pytest.mark.dds
def test_the_nodes_diagnostics_are_ok_and_name_a_stopped_bridge(ros_domain):
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain), PYTHONUNBUFFERED='1', OMP_NUM_THREADS='1')
    bridge = subprocess.Popen([sys.executable, '-m', 'hdp_sim_bridge.sim_bridge_node', '--ros-args',
                               '-p', 'camera_rate_hz:=0.0'], env=env, stdout=subprocess.DEVNULL,
                              stderr=subprocess.DEVNULL)
    controller = subprocess.Popen([sys.executable, '-m', 'hdp_controller.controller_node', '--ros-args',
                                   '-p', 'autostart:=true',
                                   '-p', 'method:=planner', '-p', 'state_timeout_s:=2.0'], env=env,
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    reader = subprocess.Popen([sys.executable, __file__, 'read', '90'], env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.DEVNULL, text=True, cwd=os.path.dirname(__file__))
    try:
        # Judged by whole arrays of the expected statuses: a node of another run that shares the
        # domain by chance (method rkd, say) publishes another set.
        expected = {'controller_node': {'lifecycle', 'model', 'joint states', 'last segment', 'liveness'},
                    'sim_bridge_node': {'real-time factor', 'front camera', 'side camera', 'episode'}}
        controller_ok, bridge_ok = {}, {}

        def all_ok(statuses):
            for node, found in (('controller_node', controller_ok), ('sim_bridge_node', bridge_ok)):
                mine = {name: s for name, s in statuses.items() if name.startswith(f'{node}: ')}
                if ({name.split(': ', 1)[1] for name in mine} == expected[node]
                        and all(level == 0 for level, _ in mine.values())):
                    found.update(mine)
            return controller_ok and bridge_ok

        _until(reader, all_ok, 60)
        assert controller_ok['controller_node: model'][1] == 'planner on cpu'
        assert controller_ok['controller_node: lifecycle'][1] == 'active'
        assert bridge_ok['sim_bridge_node: front camera'][1] == 'off (camera_rate_hz 0)'
        assert bridge_ok['sim_bridge_node: episode'][1].startswith('reach_target seed 0 variation ')

        bridge.send_signal(signal.SIGINT)
        bridge.wait(timeout=30)
        stopped = _until(reader, lambda s: s.get('controller_node: joint states', (0,))[0] == 2, 15)
        level, message = stopped[-1]['controller_node: joint states']
        assert message.startswith(f'no {topics.JOINT_STATES} for ')
        assert message.endswith(': is sim_bridge_node (or the robot driver) running?')
        assert stopped[-1]['controller_node: liveness'][0] == 2
        # On its way there it warned: late by a few periods, before the node's own timeout.
        assert any(s.get('controller_node: joint states', (0,))[0] == 1 for s in stopped)
    finally:
        for proc in (reader, controller, bridge):
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        for proc in (reader, controller, bridge):
            proc.communicate(timeout=30)
