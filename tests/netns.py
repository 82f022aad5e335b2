"""Two hosts on one machine, for tests: network namespaces joined by a veth pair.

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
permission) the test is skipped with the reason.
"""

import contextlib
import dataclasses
import json
import os
import secrets
import shutil
import signal
import subprocess

import pytest

SUBNET_PREFIX = '10.213'
_TBF_LATENCY = '50ms'      # how long a packet may wait in the bucket before it is dropped


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


def unavailable() -> str | None:
    """Why network namespaces cannot be made here, or None."""
    if os.geteuid() != 0:
        return 'network namespaces need root'
    if shutil.which('ip') is None:
        return 'no `ip` command (iproute2)'
    return None


@contextlib.contextmanager
def two_hosts(rate_mbit: float | None = None):
    """(robot, workstation): two Hosts on one /24, each reaching the other; see the module doc."""
    reason = unavailable() or (rate_mbit is not None and shutil.which('tc') is None and 'no `tc` command')
    if reason:
        pytest.skip(reason)
    token = secrets.token_hex(4)
    subnet = f'{SUBNET_PREFIX}.{int(token[:2], 16)}'
    hosts = [Host(f'hdp-{token}-{side}', f'hdp{token}{side}', f'{subnet}.{number}')
             for number, side in ((1, 'r'), (2, 'w'))]
    made = []
    try:
        for host in hosts:
            _ip_or_skip('netns', 'add', host.namespace)
            made.append(host.namespace)
        robot, workstation = hosts
        _ip_or_skip('link', 'add', robot.interface, 'netns', robot.namespace, 'type', 'veth',
                    'peer', 'name', workstation.interface, 'netns', workstation.namespace)
        for host in hosts:
            _ip('-n', host.namespace, 'addr', 'add', f'{host.address}/24', 'dev', host.interface)
            _ip('-n', host.namespace, 'link', 'set', 'lo', 'up')
            _ip('-n', host.namespace, 'link', 'set', host.interface, 'up')
            if rate_mbit is not None:
                _limit_rate(host, rate_mbit)
        yield robot, workstation
    finally:
        for host in hosts:
            _end(host._processes)
        left = [namespace for namespace in made
                if subprocess.run(['ip', 'netns', 'delete', namespace], capture_output=True).returncode != 0]
        if left:
            raise RuntimeError(f'could not delete network namespaces {left}: `ip netns delete` them by hand')


def _limit_rate(host: Host, rate_mbit: float) -> None:
    # tbf needs a bucket of at least one timer tick's worth of bytes; 10 ms of the rate is plenty.
    burst = max(int(rate_mbit * 1e6 / 8 / 100), 32 * 1024)
    argv = ['tc', 'qdisc', 'add', 'dev', host.interface, 'root', 'tbf', 'rate', f'{rate_mbit}mbit',
            'burst', str(burst), 'latency', _TBF_LATENCY]
    done = host.run(argv, capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f'cannot limit the link with tbf: {done.stderr.strip()}')


def _end(processes: list) -> None:
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


def _ip_or_skip(*args: str) -> None:
    """The first steps, where a machine without the permission (EPERM in a container) says so."""
    done = subprocess.run(['ip', *args], capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f'cannot make network namespaces: `ip {" ".join(args)}`: {done.stderr.strip()}')
