"""Two hosts on one machine: network namespaces joined by a veth pair (root only).

    with netns.two_hosts(rate_mbit=100) as (robot, workstation):
        talker = robot.popen([sys.executable, 'talker.py'], env=env)
        workstation.run([sys.executable, 'listener.py'], env=env, timeout=30)

Each call makes its own pair of namespaces, named from a random token, with the veth
ends created straight inside them (nothing appears in the machine's own namespace),
addressed on a private /24 in 10.213.0.0/16 and with loopback up (ROS 2 processes on
one host still talk over it). ``rate_mbit`` puts a token bucket (``tc`` tbf) on both
ends; netem is not available on these kernels. On the way out, however it leaves,
the processes started here are ended and both namespaces deleted, which takes the
veth pair with them. Where namespaces cannot be made (not root, no iproute2, no
permission) two_hosts raises NamespacesUnavailable with the reason.

`hdp bench link` and the two-host tests use it; both namespaces share the machine's
clock, CPUs and /dev/shm, only the network is apart.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import secrets
import shutil
import signal
import subprocess
import time

SUBNET_PREFIX = '10.213'
_TBF_LATENCY = '50ms'      # how long a packet may wait in the bucket before it is dropped
DISCOVERY_MODES = ('subnet', 'static_peers')
# Set by ros.init() in a parent process, these would hand a child the parent's Fast DDS setup.
_INHERITED_DDS_SETUP = ('ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_STATIC_PEERS', 'FASTRTPS_DEFAULT_PROFILES_FILE',
                        'FASTDDS_DEFAULT_PROFILES_FILE')


class NamespacesUnavailable(RuntimeError):
    """Network namespaces (or the rate limit) cannot be made on this machine; the message says why."""


@dataclasses.dataclass
class Host:
    """One end of the link: a network namespace, its veth interface and address."""
    namespace: str
    interface: str
    address: str
    _processes: list = dataclasses.field(default_factory=list, repr=False)

    def command(self, argv: list) -> list:
        return ['ip', 'netns', 'exec', self.namespace, *argv]

    def popen(self, argv: list, **kwargs) -> subprocess.Popen:
        """Start ``argv`` inside this host; two_hosts() ends it on the way out if it still runs."""
        process = subprocess.Popen(self.command(argv), **kwargs)     # `ip netns exec` execs: same pid
        self._processes.append(process)
        return process

    def run(self, argv: list, **kwargs) -> subprocess.CompletedProcess:
        return subprocess.run(self.command(argv), **kwargs)

    def link_bytes(self) -> tuple[int, int]:
        """(received, sent) bytes on this host's end of the link so far."""
        link, = json.loads(_ip('-n', self.namespace, '-j', '-s', 'link', 'show', 'dev', self.interface))
        return link['stats64']['rx']['bytes'], link['stats64']['tx']['bytes']

    def udp_counters(self) -> dict[str, int]:
        """This host's UDP counters so far (/proc/net/snmp: InDatagrams, RcvbufErrors: datagrams
        dropped because a socket's receive buffer was full, ...)."""
        names, values = [line.split()[1:] for line in self.run(['cat', '/proc/net/snmp'], check=True,
                                                                capture_output=True, text=True).stdout.splitlines()
                         if line.startswith('Udp:')]
        return dict(zip(names, map(int, values)))


def unavailable() -> str | None:
    """Why network namespaces cannot be made here, or None (they may still fail: no permission)."""
    if os.geteuid() != 0:
        return 'network namespaces need root'
    if shutil.which('ip') is None:
        return 'no `ip` command (iproute2)'
    return None


def discovery_env(mode: str, domain: int, peer: Host, environ=os.environ) -> dict:
    """A process's environment on one host for discovery ``mode`` ('subnet': ROS 2 Jazzy's
    ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET, 'static_peers': ROS_STATIC_PEERS=<peer>, anything
    else: neither, the localhost default), ``peer`` being the other host; ros.init() in the
    process then picks the project's Fast DDS profile for it."""
    env = {name: value for name, value in environ.items() if name not in _INHERITED_DDS_SETUP}
    env.update(ROS_DOMAIN_ID=str(domain), PYTHONUNBUFFERED='1')
    if mode == 'subnet':
        env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'SUBNET'
    elif mode == 'static_peers':
        env['ROS_STATIC_PEERS'] = peer.address
    return env


@contextlib.contextmanager
def two_hosts(rate_mbit: float | None = None):
    """(robot, workstation): two Hosts on one /24, each reaching the other; see the module doc."""
    reason = unavailable() or (rate_mbit is not None and shutil.which('tc') is None and 'no `tc` command')
    if reason:
        raise NamespacesUnavailable(reason)
    token = secrets.token_hex(4)
    subnet = f'{SUBNET_PREFIX}.{int(token[:2], 16)}'
    hosts = [Host(f'hdp-{token}-{side}', f'hdp{token}{side}', f'{subnet}.{number}')
             for number, side in ((1, 'r'), (2, 'w'))]
    made = []
    try:
        for host in hosts:
            _ip_or_refuse('netns', 'add', host.namespace)
            made.append(host.namespace)
        robot, workstation = hosts
        _ip_or_refuse('link', 'add', robot.interface, 'netns', robot.namespace, 'type', 'veth',
                      'peer', 'name', workstation.interface, 'netns', workstation.namespace)
        for host in hosts:
            _ip('-n', host.namespace, 'addr', 'add', f'{host.address}/24', 'dev', host.interface)
            _ip('-n', host.namespace, 'link', 'set', 'lo', 'up')
            _ip('-n', host.namespace, 'link', 'set', host.interface, 'up')
            if rate_mbit is not None:
                _limit_rate(host, rate_mbit)
        for host in hosts:
            _wait_for_carrier(host)
        yield robot, workstation
    finally:
        for host in hosts:
            stop_processes(host._processes)
        left = [namespace for namespace in made
                if subprocess.run(['ip', 'netns', 'delete', namespace], capture_output=True).returncode != 0]
        if left:
            raise RuntimeError(f'could not delete network namespaces {left}: `ip netns delete` them by hand')


def _wait_for_carrier(host: Host, timeout_s: float = 10.0) -> None:
    """Until the kernel reports the link up (it does so up to a second after `link set up`): Fast
    DDS leaves out interfaces that are down when a participant starts, so a process started
    before that never discovers across the link."""
    deadline = time.monotonic() + timeout_s
    while True:
        link, = json.loads(_ip('-n', host.namespace, '-j', 'link', 'show', 'dev', host.interface))
        if link['operstate'] == 'UP':
            return
        if time.monotonic() > deadline:
            raise RuntimeError(f'{host.interface} in {host.namespace} not up within {timeout_s:.0f} s '
                               f'(state {link["operstate"]})')
        time.sleep(0.05)


def _limit_rate(host: Host, rate_mbit: float) -> None:
    # tbf needs a bucket of at least one timer tick's worth of bytes; 10 ms of the rate is plenty.
    burst = max(int(rate_mbit * 1e6 / 8 / 100), 32 * 1024)
    argv = ['tc', 'qdisc', 'add', 'dev', host.interface, 'root', 'tbf', 'rate', f'{rate_mbit}mbit',
            'burst', str(burst), 'latency', _TBF_LATENCY]
    done = host.run(argv, capture_output=True, text=True)
    if done.returncode != 0:
        raise NamespacesUnavailable(f'cannot limit the link with tbf: {done.stderr.strip()}')


def stop_processes(processes: list) -> None:
    """SIGINT (a node's clean shutdown), then SIGKILL what has not ended within 10 s."""
    running = [p for p in processes if p.poll() is None]
    for process in running:
        process.send_signal(signal.SIGINT)
    for process in running:
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def _ip(*args: str) -> str:
    return subprocess.run(['ip', *args], check=True, capture_output=True, text=True).stdout


def _ip_or_refuse(*args: str) -> None:
    """The first steps, where a machine without the permission (EPERM in a container) says so."""
    done = subprocess.run(['ip', *args], capture_output=True, text=True)
    if done.returncode != 0:
        raise NamespacesUnavailable(f'cannot make network namespaces: `ip {" ".join(args)}`: {done.stderr.strip()}')
