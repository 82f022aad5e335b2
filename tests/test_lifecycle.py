"""Managed nodes: the manager's plan, and the graph brought up, paused, respawned and shut down.

Run as a script, this file is the probe the process tests start: `python test_lifecycle.py probe`.
"""

import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest
import yaml

from hdp_ros.lifecycle import transitions

NODES = ['controller_node', 'planner_node']


# --- the plan, without ROS ---------------------------------------------------------------------

@pytest.mark.unit
def test_going_up_configures_every_node_before_activating_any_in_order():
    states = {'controller_node': 'unconfigured', 'planner_node': 'unconfigured'}
    assert transitions('active', states, NODES) == [
        ('controller_node', 'configure'), ('planner_node', 'configure'),
        ('controller_node', 'activate'), ('planner_node', 'activate')]


@pytest.mark.unit
def test_going_down_takes_the_nodes_in_reverse_order():
    states = {'controller_node': 'active', 'planner_node': 'active'}
    assert transitions('inactive', states, NODES) == [('planner_node', 'deactivate'),
                                                      ('controller_node', 'deactivate')]
    assert transitions('unconfigured', states, NODES) == [
        ('planner_node', 'deactivate'), ('controller_node', 'deactivate'),
        ('planner_node', 'cleanup'), ('controller_node', 'cleanup')]
    assert transitions('finalized', {**states, 'controller_node': 'finalized'}, NODES) == [
        ('planner_node', 'shutdown')]


@pytest.mark.unit
def test_a_restarted_node_alone_is_brought_up_and_nodes_at_the_goal_are_left_alone():
    states = {'controller_node': 'unconfigured', 'planner_node': 'active'}
    assert transitions('active', states, NODES) == [('controller_node', 'configure'),
                                                    ('controller_node', 'activate')]
    assert transitions('active', {n: 'active' for n in NODES}, NODES) == []


@pytest.mark.unit
@pytest.mark.parametrize('goal, state', [('running', 'active'), ('active', 'configuring'), ('active', 'finalized')])
def test_an_unknown_goal_or_a_node_between_states_cannot_be_planned(goal, state):
    with pytest.raises(ValueError):
        transitions(goal, {'controller_node': 'active', 'planner_node': state}, NODES)


@pytest.mark.unit
def test_diagnostics_say_a_node_that_is_not_active_takes_no_work():
    from hdp_ros import diagnostics
    assert diagnostics.lifecycle_status('n', 'active').level == diagnostics.OK
    inactive = diagnostics.lifecycle_status('n', 'inactive')
    assert inactive.level == diagnostics.WARN and 'takes no work' in inactive.message
    failed = diagnostics.lifecycle_status('n', 'unconfigured', 'cannot load the agent: no file x.pt')
    assert failed.level == diagnostics.ERROR and 'no file x.pt' in failed.message


# --- the graph's processes ---------------------------------------------------------------------

def _env(domain: int) -> dict:
    return dict(os.environ, ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1', OMP_NUM_THREADS='1')


class _Output:
    """A process's stdout lines, read in a thread, waited on."""

    def __init__(self, proc):
        self.lines, self._changed = [], threading.Condition()
        threading.Thread(target=self._read, args=(proc.stdout,), daemon=True).start()

    def _read(self, stream):
        for line in stream:
            with self._changed:
                self.lines.append(line.rstrip('\n'))
                self._changed.notify_all()

    def wait_for(self, text: str, timeout: float, since: int = 0) -> int:
        """The index of the first line from ``since`` on containing text; AssertionError if none comes."""
        def found():
            return next((i for i, line in enumerate(self.lines[since:], since) if text in line), None)
        with self._changed:
            index = self._changed.wait_for(lambda: found() is not None, timeout)
        assert index is not None or found() is not None, f'no {text!r} within {timeout} s:\n' + '\n'.join(self.lines)
        return found()


def _hdp(env, *args, timeout=60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, '-m', 'hdp_tools.cli.main', *args], env=env, text=True,
                          capture_output=True, timeout=timeout)


@pytest.mark.dds
def test_hdp_launch_manages_the_nodes_through_pause_respawn_and_shutdown(ros_domain):
    """`hdp launch` starts a lifecycle manager that brings controller_node, then planner_node, to
    active; the standard services answer any client (`hdp lifecycle`); an instruction sent while
    the planner is inactive is refused on /hdp/outcome; the manager's pause and resume take both
    down and up; a SIGKILLed controller respawned by launch is brought back to active; Ctrl-C ends
    everything cleanly."""
    env = _env(ros_domain)
    launch = subprocess.Popen([sys.executable, '-m', 'hdp_tools.cli.main', 'launch', '--nodes',
                               'planner_node,controller_node', '--respawn', 'controller_node',
                               '-p', 'controller_node:method:=planner', '-p', 'controller_node:use_sim_time:=false'],
                              env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    output = _Output(launch)
    try:
        up = output.wait_for('[lifecycle_manager] ', 60)
        order = [output.wait_for(f'{step} {node}: done', 180, up) for step, node in
                 (('configure', 'controller_node'), ('configure', 'planner_node'),
                  ('activate', 'controller_node'), ('activate', 'planner_node'))]
        assert order == sorted(order), '\n'.join(output.lines)
        output.wait_for('controller_node, planner_node active in', 30)

        listed = _hdp(env, 'lifecycle', 'nodes')
        assert listed.stdout.split() == ['/controller_node', '/planner_node'], listed
        assert _hdp(env, 'lifecycle', 'get', '/planner_node').stdout.strip() == 'active'

        probe = subprocess.run([sys.executable, __file__, 'probe'], env=env, text=True, capture_output=True,
                               timeout=180)
        assert probe.returncode == 0, probe.stderr
        facts = json.loads(probe.stdout.strip().splitlines()[-1])
        assert facts['deactivate'] is True and facts['after_deactivate'] == 'inactive'
        refused, = facts['outcomes']
        assert refused['instruction'] == 'open the drawer' and refused['result'] == 'refused'
        assert refused['reason'].startswith('planner_node is inactive'), refused
        assert facts['activate'] is True and facts['after_activate'] == 'active'
        assert facts['pause'] == [True, 'controller_node, planner_node inactive']
        assert facts['paused'] == {'controller_node': 'inactive', 'planner_node': 'inactive'}
        assert facts['is_active_paused'] is False
        assert facts['resume'] == [True, 'controller_node, planner_node active']
        assert facts['is_active'] is True
        # A transition that makes no sense from the state is refused, and the node lives on.
        assert facts['configure_active'] is False and facts['after_configure_active'] == 'active'

        killed_at = len(output.lines)
        pid = int(next(line for line in reversed(output.lines) if 'started controller_node (pid' in line)
                  .split('pid ')[1].rstrip(')'))
        os.kill(pid, signal.SIGKILL)
        output.wait_for('respawning it', 30, killed_at)
        output.wait_for('[controller_node] ', 60, killed_at)
        output.wait_for('controller_node is back and unconfigured: bringing it to active', 120, killed_at)
        output.wait_for('ready: method planner', 120, killed_at)
        assert _hdp(env, 'lifecycle', 'get', '/controller_node').stdout.strip() == 'active'
    finally:
        launch.send_signal(signal.SIGINT)
        launch.wait(timeout=60)
    text = '\n'.join(output.lines)
    assert launch.returncode == 0, text
    assert '[planner_node] ' in text and 'shutting down: planner_node shut down' in text
    assert 'Traceback' not in text, text


@pytest.mark.dds
def test_a_node_that_cannot_configure_stays_unconfigured_says_why_and_refuses_instructions(ros_domain, tmp_path):
    """A missing checkpoint under `hdp launch`: planner_node's configure fails (it says why), the
    manager names the node that refused and stops the bring-up, and the node, alive and
    unconfigured, answers an instruction with a refusal on /hdp/outcome."""
    env = _env(ros_domain)
    launch = subprocess.Popen([sys.executable, '-m', 'hdp_tools.cli.main', 'launch', '--nodes',
                               'planner_node,controller_node', '-p', 'controller_node:method:=planner',
                               '-p', 'controller_node:use_sim_time:=false',
                               '-p', f'planner_node:checkpoint:={tmp_path / "missing.pt"}'],
                              env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    output = _Output(launch)
    try:
        output.wait_for('[planner_node] ', 60)
        output.wait_for('[planner_node]: cannot configure: cannot load the next-best-pose agent', 120)
        output.wait_for('could not configure planner_node: it refused (its status says why); bring-up stopped', 30)
        assert _hdp(env, 'lifecycle', 'get', '/planner_node').stdout.strip() == 'unconfigured'
        echo = subprocess.Popen([sys.executable, '-m', 'hdp_tools.cli.main', 'topic', 'echo', '--once',
                                 '--timeout', '30', '/hdp/outcome', 'std_msgs/msg/String'],
                                env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        time.sleep(3.0)                            # the echo up and matched before the instruction goes
        sent = _hdp(env, 'topic', 'pub', '--once', '-w', '1', '--max-wait', '30', '/hdp/instruction',
                    'std_msgs/msg/String', "{data: 'open the drawer'}")
        assert sent.returncode == 0, sent.stderr
        out, err = echo.communicate(timeout=60)
        outcome = json.loads(next(yaml.safe_load_all(out))['data'])
        assert outcome['result'] == 'refused' and outcome['reason'].startswith('planner_node is unconfigured'), out
    finally:
        launch.send_signal(signal.SIGINT)
        launch.wait(timeout=60)
    assert launch.returncode == 0, '\n'.join(output.lines)


def probe() -> None:
    """Drive the running graph through its lifecycle services and the manager's; print what it saw."""
    import rclpy
    from rclpy.executors import MultiThreadedExecutor
    from std_srvs.srv import Trigger

    from hdp_msgs_py import topics
    from hdp_msgs_py.msg import String
    from hdp_ros import ros
    from hdp_ros.lifecycle import LifecycleClient

    ros.init(args=sys.argv)
    node = ros.Node('lifecycle_probe')
    outcomes = []
    node.create_subscription(String, topics.OUTCOME, lambda m: outcomes.append(json.loads(m.data)),
                             topics.INSTRUCTION_QOS)
    instruction = node.create_publisher(String, topics.INSTRUCTION, topics.INSTRUCTION_QOS)
    executor = MultiThreadedExecutor(num_threads=2)
    executor.add_node(node)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    planner, controller = LifecycleClient(node, 'planner_node'), LifecycleClient(node, 'controller_node')
    assert planner.wait_for_services(30) and controller.wait_for_services(30)
    facts = {'deactivate': planner.change_state('deactivate', 30), 'after_deactivate': planner.get_state(10)}
    end = time.monotonic() + 30
    while instruction.get_subscription_count() == 0 and time.monotonic() < end:
        time.sleep(0.1)
    instruction.publish(String(data='open the drawer'))
    end = time.monotonic() + 30
    while not outcomes and time.monotonic() < end:
        time.sleep(0.1)
    facts.update(outcomes=list(outcomes), activate=planner.change_state('activate', 30),
                 after_activate=planner.get_state(10))

    def call(service: str):
        client = node.create_client(Trigger, f'/lifecycle_manager/{service}')
        assert client.wait_for_service(30), service
        done = threading.Event()
        future = client.call_async(Trigger.Request())
        future.add_done_callback(lambda _: done.set())
        assert done.wait(120), service
        return future.result()

    pause = call('pause')
    facts.update(pause=[pause.success, pause.message],
                 paused={'controller_node': controller.get_state(10), 'planner_node': planner.get_state(10)},
                 is_active_paused=call('is_active').success)
    resume = call('resume')
    facts.update(resume=[resume.success, resume.message], is_active=call('is_active').success,
                 configure_active=planner.change_state('configure', 30),
                 after_configure_active=planner.get_state(10))
    print(json.dumps(facts), flush=True)
    executor.shutdown()
    # The spin thread must have left the wait set before the node goes: destroyed under it, the
    # node's middleware entities outlive rclpy, and the process aborts at exit (7 runs of 20 did).
    spinner.join()
    node.destroy_node()
    rclpy.try_shutdown()


@pytest.mark.dds
def test_instructions_running_and_waiting_at_sigint_end_shutdown_on_the_outcome_topic(ros_domain):
    """Ctrl-C on planner_node: the running instruction and the queued one each get an outcome
    'shutdown' before the process ends (rclpy's own signal handler would have shut the
    middleware down first, and the outcomes with it)."""
    env = _env(ros_domain)
    planner = subprocess.Popen([sys.executable, '-m', 'hdp_planner.planner_node', '--ros-args',
                                '-p', 'autostart:=true', '-p', 'camera_timeout_s:=300.0', '-p', 'state_timeout_s:=300.0',
                                '-p', 'queue_policy:=queue'],
                               env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    output = _Output(planner)
    echo = subprocess.Popen([sys.executable, '-m', 'hdp_tools.cli.main', 'topic', 'echo', '/hdp/outcome',
                             'std_msgs/msg/String'],
                            env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        output.wait_for('ready: agent', 120)
        for text in ('open the drawer', 'close the drawer'):
            sent = _hdp(env, 'topic', 'pub', '--once', '-w', '1', '--max-wait', '30', '/hdp/instruction',
                        'std_msgs/msg/String', f"{{data: '{text}'}}")
            assert sent.returncode == 0, sent.stderr
        output.wait_for("instruction 'close the drawer' queued", 30)
    finally:
        planner.send_signal(signal.SIGINT)
        planner.wait(timeout=30)
        time.sleep(2.0)                            # for the outcomes to reach the echo
        echo.send_signal(signal.SIGINT)
    out, err = echo.communicate(timeout=30)
    assert planner.returncode == 0, '\n'.join(output.lines)
    outcomes = [json.loads(doc['data']) for doc in yaml.safe_load_all(out) if doc]
    assert [(o['instruction'], o['result']) for o in outcomes] == [
        ('close the drawer', 'shutdown'), ('open the drawer', 'shutdown')], (out, err)


if __name__ == '__main__' and sys.argv[1:2] == ['probe']:
    probe()
