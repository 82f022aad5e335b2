"""`hdp dds`: the TLS profile's credentials and discovery server, and the environment that gives a
process started some other way (a C++ driver under `ros2 launch`) the project's Fast DDS profile.

    hdp dds credentials cell/ robot workstation     # a CA, and a certificate per host
    HDP_DDS_TLS_DIR=cell/robot HDP_DDS_DISCOVERY_SERVER=10.0.0.1 hdp dds server
    eval "$(hdp dds env)"                           # then ros2 launch franka_bringup ...
"""

import functools
import os
import re
import secrets
import shlex
import shutil
import socket
import subprocess
import sys
import tempfile
from pathlib import Path

from . import fastdds, ros

# What `openssl req` and `openssl x509` read: the CA may sign certificates only; a host's
# certificate serves both ends of a TLS connection (every participant accepts and connects).
_OPENSSL_CONFIG = """\
[req]
distinguished_name = subject
prompt = no
[subject]
CN = hdp
[ca]
basicConstraints = critical, CA:TRUE
keyUsage = critical, keyCertSign, cRLSign
subjectKeyIdentifier = hash
[host]
basicConstraints = critical, CA:FALSE
keyUsage = critical, digitalSignature
extendedKeyUsage = serverAuth, clientAuth
subjectKeyIdentifier = hash
authorityKeyIdentifier = keyid
"""
_HOST_NAME = re.compile(r'[A-Za-z0-9][A-Za-z0-9_.-]*')


def configure_credentials(parser) -> None:
    """Make the TLS profile's credentials: a CA for the cell and a certificate per host (openssl).

    OUT/ca.key and OUT/ca.pem are the CA (made once, reused to add hosts later; keep ca.key
    off the robot's network); OUT/HOST/ holds ca.pem, cert.pem and key.pem, what HDP_DDS_TLS_DIR
    names on that host. Any certificate the CA signed is let in: the CA is the cell's one key.
    """
    parser.add_argument('out', type=Path, help='the cell\'s directory')
    parser.add_argument('hosts', nargs='+', metavar='HOST', help='a name per host (robot, workstation)')
    parser.add_argument('--days', type=int, default=825, help='validity of new certificates (default 825)')
    parser.set_defaults(func=run_credentials)


def configure_server(parser) -> None:
    """Serve discovery for the TLS profile until Ctrl-C, on the port of HDP_DDS_DISCOVERY_SERVER.

    Run it on the host HDP_DDS_DISCOVERY_SERVER names (the robot's), with that host's
    HDP_DDS_TLS_DIR; every process on the TLS profile finds the others through it.
    """
    parser.set_defaults(func=run_server)


def configure_env(parser) -> None:
    """Print `export` lines giving a process started some other way the project's Fast DDS profile.

    What hdp_ros.ros.init() sets for this environment (ROS_AUTOMATIC_DISCOVERY_RANGE,
    ROS_STATIC_PEERS, HDP_DDS_TLS_DIR, ...): `eval "$(hdp dds env)"` before `ros2 launch` of a
    driver that does not call it. Nothing is printed where the user's own set-up stands.
    """
    parser.set_defaults(func=run_env)


def run_credentials(args) -> int:
    openssl = shutil.which('openssl')
    if openssl is None:
        print('hdp dds credentials: needs the openssl command (apt install openssl)', file=sys.stderr)
        return 1
    bad = [host for host in args.hosts if not _HOST_NAME.fullmatch(host) or (args.out / host).exists()]
    if bad:
        print(f'hdp dds credentials: {", ".join(bad)}: not a plain name, or already in {args.out}', file=sys.stderr)
        return 2
    make_credentials(openssl, args.out, args.hosts, args.days)
    for host in args.hosts:
        print(f'{host}: HDP_DDS_TLS_DIR={args.out / host}')
    return 0


def make_credentials(openssl: str, out: Path, hosts: list, days: int) -> None:
    """The CA in ``out`` (made unless there), and ``out``/HOST/{ca.pem,cert.pem,key.pem} for each host."""
    out.mkdir(parents=True, exist_ok=True)
    ca_key, ca_cert = out / 'ca.key', out / 'ca.pem'
    with tempfile.TemporaryDirectory() as scratch:
        config = Path(scratch) / 'openssl.cnf'
        config.write_text(_OPENSSL_CONFIG)

        def run(*args):
            # Without OPENSSL_CONF: a shell on the TLS profile has it set to what Fast DDS needs.
            env = {name: value for name, value in os.environ.items() if name != 'OPENSSL_CONF'}
            subprocess.run([openssl, *map(str, args)], check=True, capture_output=True, env=env)

        if not ca_key.exists():
            _new_key(run, ca_key)
            run('req', '-config', config, '-x509', '-new', '-key', ca_key, '-subj', '/CN=HDP cell CA',
                '-days', days, '-extensions', 'ca', '-out', ca_cert)
        for host in hosts:
            folder = out / host
            folder.mkdir()
            _new_key(run, folder / 'key.pem')
            request = Path(scratch) / f'{host}.csr'
            run('req', '-config', config, '-new', '-key', folder / 'key.pem', '-subj', f'/CN={host}', '-out', request)
            run('x509', '-req', '-in', request, '-CA', ca_cert, '-CAkey', ca_key, '-set_serial',
                f'0x{secrets.token_hex(16)}', '-days', days, '-extfile', config, '-extensions', 'host',
                '-out', folder / 'cert.pem')
            shutil.copyfile(ca_cert, folder / 'ca.pem')


def _new_key(run, path: Path) -> None:
    """A P-256 private key at ``path``, readable by its owner only from the start."""
    os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    run('genpkey', '-algorithm', 'EC', '-pkeyopt', 'ec_paramgen_curve:P-256', '-out', path)


class DiscoveryServer(ros.Node):
    """A participant with the TLS profile's server side; the node only names it on the graph."""

    def __init__(self, settings: fastdds.TlsSettings):
        super().__init__('hdp_discovery_server')
        self.get_logger().info(f'serving discovery over TLS at {settings.server_address}:{settings.server_port}')


def run_server(args) -> int:
    try:
        settings = fastdds.tls_settings(os.environ)
        if settings is None:
            raise ValueError('set HDP_DDS_TLS_DIR and HDP_DDS_DISCOVERY_SERVER (hdp_ros/README.md)')
    except ValueError as err:
        print(f'hdp dds server: {err}', file=sys.stderr)
        return 2
    if _port_taken(settings.server_port):
        # Fast DDS would only log that it cannot bind, and serve no one.
        print(f'hdp dds server: port {settings.server_port} is taken (another server?)', file=sys.stderr)
        return 1
    server_profile = fastdds.tls_profile(settings, server=True)
    os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(fastdds.write_profile(os.environ, 'tls_server', server_profile))
    ros.run(functools.partial(DiscoveryServer, settings), [sys.argv[0]], 'hdp_discovery_server')
    return 0


def _port_taken(port: int) -> bool:
    with socket.socket() as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)     # as Fast DDS's acceptor
        try:
            probe.bind(('', port))
        except OSError:
            return True
    return False


def run_env(args) -> int:
    environ = dict(os.environ)
    try:
        ros.use_project_profile(environ)
    except ValueError as err:
        print(f'hdp dds env: {err}', file=sys.stderr)
        return 2
    for name in sorted(environ):
        if environ[name] != os.environ.get(name):
            print(f'export {name}={shlex.quote(environ[name])}')
    return 0
