"""hdp_ros.ros: the Fast DDS profile every process gets, what it does to the sockets, and the
shared memory of dead processes it removes."""

import fcntl
import os
import re
import signal
import socket
import threading
import time
import xml.etree.ElementTree as ElementTree

import pytest

from hdp_ros import fastdds, ros, shm
from test_dds_processes import finish, start

pytestmark = pytest.mark.unit


NS = {'f': fastdds.NAMESPACE}


def test_the_localhost_profile_is_applied_by_default():
    environ = {'ROS_DOMAIN_ID': '7'}
    assert ros.use_project_profile(environ) == 'localhost'
    assert environ == {'ROS_DOMAIN_ID': '7', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SYSTEM_DEFAULT',
                       'FASTRTPS_DEFAULT_PROFILES_FILE': str(ros.FASTDDS_LOCALHOST_PROFILE)}
    assert ros.use_project_profile({'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}) == 'localhost'


@pytest.mark.parametrize('choice', [
    {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'OFF'}, {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SYSTEM_DEFAULT'},
    {'ROS_AUTOMATIC_DISCOVERY_RANGE': 'OFF', 'ROS_STATIC_PEERS': '192.168.1.7'},
    {'FASTRTPS_DEFAULT_PROFILES_FILE': '/etc/mine.xml'}, {'FASTDDS_DEFAULT_PROFILES_FILE': '/etc/mine.xml'},
    {'ROS_DISCOVERY_SERVER': '10.0.0.1:11811'}, {'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'},
    {'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET'}])
def test_a_users_own_middleware_choice_is_left_alone(choice):
    environ = dict(choice)
    assert ros.use_project_profile(environ) is None
    assert environ == choice


def _network(environ) -> ElementTree.Element:
    assert ros.use_project_profile(environ) == 'network'
    assert environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'SYSTEM_DEFAULT'     # rmw takes the file as it is
    return ElementTree.parse(environ['FASTRTPS_DEFAULT_PROFILES_FILE']).getroot()


def _initial_peers(root) -> list[str]:
    return [a.text for a in root.findall('.//f:initialPeersList/f:locator/f:udpv4/f:address', NS)]


def test_static_peers_get_the_network_profile_unicast_only(tmp_path):
    root = _network({'ROS_STATIC_PEERS': '10.0.0.2; localhost;10.0.0.3', 'XDG_RUNTIME_DIR': str(tmp_path)})
    assert _initial_peers(root) == ['127.0.0.1', '10.0.0.2', '10.0.0.3']
    # An empty unicast locator: no multicast listening, as rmw_fastrtps_cpp's LOCALHOST range.
    assert root.find('.//f:builtin/f:metatrafficUnicastLocatorList/f:locator', NS) is not None
    assert int(root.find('.//f:transport_descriptor[f:type="SHM"]/f:segment_size', NS).text) > 640 * 480 * 3 * 4
    assert not root.findall('.//f:interfaceWhiteList', NS)                 # every interface
    lease = root.find('.//f:leaseAnnouncement', NS)
    assert (lease.findtext('f:sec', namespaces=NS), lease.findtext('f:nanosec', namespaces=NS)) == ('0', '500000000')


@pytest.mark.parametrize('peers, expected', [('', ['127.0.0.1', '239.255.0.1']),
                                             ('10.0.0.2', ['127.0.0.1', '10.0.0.2', '239.255.0.1'])])
def test_subnet_gets_the_network_profile_with_multicast(tmp_path, peers, expected):
    root = _network({'ROS_AUTOMATIC_DISCOVERY_RANGE': 'SUBNET', 'ROS_STATIC_PEERS': peers,
                     'XDG_RUNTIME_DIR': str(tmp_path)})
    assert _initial_peers(root) == expected
    assert root.find('.//f:builtin/f:metatrafficUnicastLocatorList', NS) is None


def test_a_child_keeps_the_profile_its_parent_chose(tmp_path):
    parent = {'ROS_STATIC_PEERS': '10.0.0.2', 'XDG_RUNTIME_DIR': str(tmp_path)}
    ros.use_project_profile(parent)
    child = dict(parent)
    assert ros.use_project_profile(child) is None and child == parent
    again = {'ROS_STATIC_PEERS': '10.0.0.2', 'XDG_RUNTIME_DIR': str(tmp_path)}
    ros.use_project_profile(again)
    assert again == parent                 # the same set-up, the same file


def test_a_static_peer_that_does_not_resolve_is_refused(tmp_path):
    with pytest.raises(ValueError, match="ROS_STATIC_PEERS: cannot resolve 'no-such-host.invalid'"):
        ros.use_project_profile({'ROS_STATIC_PEERS': 'no-such-host.invalid', 'XDG_RUNTIME_DIR': str(tmp_path)})


def test_profiles_are_written_only_where_no_one_else_can_write(tmp_path):
    (tmp_path / 'hdp').mkdir(mode=0o777)
    (tmp_path / 'hdp').chmod(0o777)
    with pytest.raises(PermissionError, match='others cannot write'):
        ros.use_project_profile({'ROS_STATIC_PEERS': '10.0.0.2', 'XDG_RUNTIME_DIR': str(tmp_path)})


@pytest.fixture
def credentials(tmp_path):
    """A host's credential files as `hdp dds credentials` names them (empty: only their presence counts here)."""
    folder = tmp_path / 'robot'
    folder.mkdir()
    for name in fastdds.TLS_FILES.values():
        (folder / name).touch()
    return folder


def _tls_environ(credentials, **more) -> dict:
    return {'HDP_DDS_TLS_DIR': str(credentials), 'HDP_DDS_DISCOVERY_SERVER': '10.0.0.1:42111',
            'XDG_RUNTIME_DIR': str(credentials.parent), **more}


def test_the_tls_profile_is_a_discovery_client_over_tls_alone(credentials):
    environ = _tls_environ(credentials, ROS_STATIC_PEERS='10.0.0.2', ROS_AUTOMATIC_DISCOVERY_RANGE='SUBNET')
    assert ros.use_project_profile(environ) == 'tls'
    assert environ['OPENSSL_CONF'] == str(fastdds.REQUIRE_PEER_CERTIFICATE)
    assert environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'SYSTEM_DEFAULT'
    root = ElementTree.parse(environ['FASTRTPS_DEFAULT_PROFILES_FILE']).getroot()
    transport, = root.findall('.//f:transport_descriptor', NS)
    assert transport.findtext('f:type', namespaces=NS) == 'TCPv4'
    assert transport.findtext('f:listening_ports/f:port', namespaces=NS) == '0'
    assert {element: transport.findtext(f'f:tls/f:{element}', namespaces=NS) for element in fastdds.TLS_FILES} == {
        element: str(credentials / name) for element, name in fastdds.TLS_FILES.items()}
    assert root.findtext('.//f:useBuiltinTransports', namespaces=NS) == 'false'
    assert root.findtext('.//f:discoveryProtocol', namespaces=NS) == 'CLIENT'
    server = root.find('.//f:RemoteServer//f:tcpv4', NS)
    assert [server.findtext(f'f:{n}', namespaces=NS) for n in ('address', 'physical_port', 'port')] == [
        '10.0.0.1', '42111', '42111']
    assert not root.findall('.//f:initialPeersList', NS)            # the static peers play no part


def test_the_discovery_servers_profile_listens_on_its_port(credentials):
    settings = fastdds.tls_settings(_tls_environ(credentials))
    root = ElementTree.fromstring(fastdds.tls_profile(settings, server=True))
    assert root.findtext('.//f:listening_ports/f:port', namespaces=NS) == '42111'
    assert root.findtext('.//f:discoveryProtocol', namespaces=NS) == 'SERVER'
    assert root.findtext('.//f:rtps/f:prefix', namespaces=NS) == '44.53.00.5f.45.50.52.4f.53.49.4d.41'
    assert root.find('.//f:builtin/f:metatrafficUnicastLocatorList//f:tcpv4/f:address', NS).text == '10.0.0.1'
    assert root.find('.//f:discoveryServersList', NS) is None


@pytest.mark.parametrize('change, why', [
    ({'HDP_DDS_DISCOVERY_SERVER': None}, 'needs both'),
    ({'HDP_DDS_DISCOVERY_SERVER': '10.0.0.1:port'}, 'must be a number'),
    ({'FASTRTPS_DEFAULT_PROFILES_FILE': '/etc/mine.xml'}, 'FASTRTPS_DEFAULT_PROFILES_FILE set up Fast DDS otherwise'),
    ({'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'}, 'unset RMW_IMPLEMENTATION')])
def test_a_tls_set_up_that_would_not_be_tls_is_refused(credentials, change, why):
    environ = {name: value for name, value in {**_tls_environ(credentials), **change}.items() if value}
    with pytest.raises(ValueError, match=why):
        ros.use_project_profile(environ)


def test_tls_without_its_credentials_is_refused(credentials):
    (credentials / 'key.pem').unlink()
    with pytest.raises(ValueError, match='lacks key.pem'):
        ros.use_project_profile(_tls_environ(credentials))


def test_a_child_keeps_the_tls_profile_its_parent_chose(credentials):
    parent = _tls_environ(credentials)
    ros.use_project_profile(parent)
    child = dict(parent, OPENSSL_CONF='/elsewhere.cnf')
    assert ros.use_project_profile(child) == 'tls'
    assert child == parent


def test_the_profile_keeps_to_loopback_with_a_segment_that_holds_a_camera_frame():
    ns = {'f': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
    root = ElementTree.parse(ros.FASTDDS_LOCALHOST_PROFILE).getroot()
    shm = int(root.find('.//f:transport_descriptor[f:type="SHM"]/f:segment_size', ns).text)
    assert shm > 640 * 480 * 3 * 4                     # several 640x480 rgb8 frames in flight
    assert [a.text for a in root.findall('.//f:interfaceWhiteList/f:address', ns)] == ['127.0.0.1']
    assert root.find('.//f:useBuiltinTransports', ns).text == 'false'
    assert not root.findall('.//f:metatrafficMulticastLocatorList', ns)


def _udp_addresses(pid: int) -> list[str]:
    """Local IPv4 addresses of the UDP sockets process ``pid`` holds."""
    inodes = set()
    for fd in os.listdir(f'/proc/{pid}/fd'):
        try:
            target = os.readlink(f'/proc/{pid}/fd/{fd}')
        except OSError:
            continue
        if target.startswith('socket:['):
            inodes.add(target[8:-1])
    addresses = []
    with open(f'/proc/{pid}/net/udp') as table:
        for line in list(table)[1:]:
            fields = line.split()
            if fields[9] in inodes:
                addresses.append(socket.inet_ntoa(bytes.fromhex(fields[1].split(':')[0])[::-1]))
    return addresses


@pytest.mark.dds
def test_a_node_listens_on_loopback_only(ros_domain):
    sub = start(ros_domain, 'sub', 'string', '--timeout', '30')
    try:
        deadline = time.monotonic() + 20
        while not (addresses := _udp_addresses(sub.pid)) and time.monotonic() < deadline:
            time.sleep(0.2)
        time.sleep(1.0)
        addresses = _udp_addresses(sub.pid)
    finally:
        sub.terminate()
        finish(sub)
    assert addresses and set(addresses) == {'127.0.0.1'}, addresses


def _segments_of(pid: int) -> set[str]:
    """The Fast DDS segments process ``pid`` owns: it holds their lock files open."""
    segments = set()
    for fd in os.listdir(f'/proc/{pid}/fd'):
        try:
            target = os.readlink(f'/proc/{pid}/fd/{fd}')
        except OSError:
            continue
        if match := re.fullmatch(r'/dev/shm/(fastrtps_[0-9a-z]{16})_el', target):
            segments.add(match.group(1))
    return segments


@pytest.mark.dds
def test_a_sigkilled_nodes_shared_memory_is_gone_once_a_node_starts_again(ros_domain):
    def node():
        proc = start(ros_domain, 'pub', 'string', '--count', '1', '--linger', '60')
        proc.stdout.readline()                  # it has published: its participant is up
        return proc

    first = node()
    segments = _segments_of(first.pid)
    time.sleep(shm.MIN_AGE_S)                   # lock files younger than this are left alone
    first.kill()
    first.communicate()
    assert segments and all((shm.SHM_DIR / s).is_file() for s in segments)      # SIGKILL cleans nothing
    assert {p.name for p in shm.dead_segments()} >= segments
    second = node()                             # the restart: ros.init() removes them
    try:
        left = [s for s in segments if (shm.SHM_DIR / s).exists() or (shm.SHM_DIR / f'{s}_el').exists()]
        alive = _segments_of(second.pid)
        assert alive and all((shm.SHM_DIR / s).is_file() for s in alive)       # a live one's stays
    finally:
        second.terminate()
        second.communicate()
    assert left == []


def test_only_segments_whose_lock_nobody_holds_are_removed(tmp_path):
    def segment(name: str, age_s: float) -> None:
        for path in (tmp_path / name, tmp_path / f'{name}_el'):
            path.touch()
            os.utime(path, (time.time() - age_s,) * 2)

    segment('fastrtps_00000000000000d1', 60.0)          # owner gone
    segment('fastrtps_00000000000000a1', 60.0)          # owner alive: holds the lock
    segment('fastrtps_00000000000000c1', 0.5)           # just created: maybe not locked yet
    (tmp_path / 'fastrtps_port7411').touch()
    (tmp_path / 'fastrtps_port7411_el').touch()          # a port: Fast DDS's own to reset
    held = os.open(tmp_path / 'fastrtps_00000000000000a1_el', os.O_RDONLY)
    fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)    # another open file description: as another process
    try:
        assert shm.dead_segments(tmp_path) == [tmp_path / 'fastrtps_00000000000000d1']
        assert shm.remove_dead_segments(tmp_path) == 1
    finally:
        os.close(held)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        'fastrtps_00000000000000a1', 'fastrtps_00000000000000a1_el', 'fastrtps_00000000000000c1',
        'fastrtps_00000000000000c1_el', 'fastrtps_port7411', 'fastrtps_port7411_el']


def test_liveness_names_silent_joint_states_and_a_clock_that_stands_still():
    from hdp_ros.liveness import Liveness
    live = Liveness(timeout_s=2.0)
    assert live.problem(wall_s=0.0, clock_s=10.0) is None          # nothing heard yet: not judged
    live.heard(1.0)
    assert live.problem(2.5, 11.0) is None
    assert live.problem(3.5, 12.0).startswith('no /joint_states for 2.5 s (wall clock)')
    live.heard(4.0)
    assert live.problem(5.0, 12.0) is None                          # the clock last moved at 3.5
    live.heard(6.0)
    assert live.problem(6.0, 12.0).startswith("the node's clock has not moved for 2.5 s")
    assert live.problem(6.1, 12.1) is None
    live.excuse(20.0)                                               # busy planning from 6.1 to 20.0
    assert live.problem(20.5, 12.1) is None and live.problem(22.1, 12.1) is not None
    with pytest.raises(ValueError):
        Liveness(0.0)


def test_a_node_that_did_not_run_blames_itself_not_the_robot():
    """A node stopped (SIGSTOP) or starved for longer than the timeout sees its own gap between
    two watchdog calls: that silence is excused, and only silence after it names the robot."""
    from hdp_ros.liveness import Liveness
    live = Liveness(timeout_s=5.0)
    live.heard(0.0)
    for t in (0.5, 1.0):
        assert live.stalled(t) is None and live.problem(t, t) is None
    assert live.stalled(21.0).startswith('this node itself did not run for 20.0 s')   # stopped 1.0-21.0
    assert live.problem(21.0, 21.0) is None                         # not 'no /joint_states for 21 s'
    assert live.stalled(21.5) is None and live.problem(21.5, 21.5) is None
    for t in (22.0, 22.5, 23.0, 23.5, 24.0, 24.5, 25.0, 25.5, 26.0, 26.5):    # the watchdog runs again ...
        assert live.stalled(t) is None
    assert live.problem(26.5, 26.5).startswith('no /joint_states for 5.5 s')    # ... and the robot is silent


class _Quiet(ros.Node):
    PARAMETERS = {}

    def __init__(self):
        super().__init__('quiet')


@pytest.mark.dds
@pytest.mark.parametrize('shutdown', ['context_down', 'signal', 'none'])
def test_run_takes_an_error_from_a_shutdown_mid_take_as_the_shutdown_it_is(monkeypatch, ros_domain, shutdown):
    """An error out of the executor while the process shuts down: the context went down under it
    (context_down), or Ctrl-C came (signal: run's own handler asked the loop to stop). With
    neither it is a bug, and it propagates."""
    def spin_once(executor, timeout_sec=None):
        if shutdown == 'context_down':
            ros.rclpy.shutdown()
        elif shutdown == 'signal':
            signal.raise_signal(signal.SIGINT)
        raise RuntimeError("Unable to convert call argument '0' to Python object")
    monkeypatch.setenv('ROS_DOMAIN_ID', str(ros_domain))
    monkeypatch.setattr(ros.SingleThreadedExecutor, 'spin_once', spin_once)
    previous = signal.getsignal(signal.SIGINT)
    try:
        if shutdown == 'none':
            with pytest.raises(RuntimeError, match='Unable to convert'):
                ros.run(_Quiet, ['quiet'])
        else:
            ros.run(_Quiet, ['quiet'])
    finally:
        signal.signal(signal.SIGINT, previous)
        ros.rclpy.try_shutdown()
    assert not ros.rclpy.ok()
